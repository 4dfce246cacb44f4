//! The Generate panel's engine: the generator running on burn's wgpu backend on the SAME
//! WebGPU device as egui. Generation runs as an async task (GPU readbacks are awaited); the
//! result is rigged to the body once, then re-posed by LBS every time the pose changes.
//!
//! The trained demo model (`models/demo.safetensors` next to the page, copied there from
//! `assets/models/` by `cargo xtask build-web`) is fetched at start-up; generations asked for
//! before it arrives wait for it. Without it the generator keeps deterministic random
//! weights and the panel says so.

use std::cell::RefCell;
use std::rc::Rc;

use crate::platform::fetch_bytes;
use eframe::egui_wgpu;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::burn::tensor::wgpu::WgpuSetup;
use getavatar_core::burn::tensor::{Device, Tensor};
use getavatar_core::generator::checkpoint::{config_with_saved_resolutions, load_generator_and_modes};
use getavatar_core::generator::network::synthesis::Triplanes;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{
    default_psi, recolor_async, seed_latents, warm_surface_kernels, BodyContext, Generator, LatentModes, Styles,
};
use getavatar_core::generator::readback::ReadbackError;
use getavatar_core::generator::rigging::generate_rigged_async;
use getavatar_core::generator::rigging::{warm_bake_kernels, BakedTexture, RiggedAvatar};
use getavatar_core::reconstruction::encoder::load_encoder_for;
use getavatar_core::util::profile;

use crate::automation::Compute;
use crate::reconstruct::{colours_in_worker, generate_in_worker, warm_worker, WorkerField};
use crate::texture_field::{fell_back, TextureField, ON_PAGE, ON_WORKER};

/// Where the page finds the trained demo model (relative to the page).
pub const MODEL_URL: &str = "models/demo.safetensors";
/// Which models the build ships (`{"demo": "demo.safetensors", "demo_d": "demo_d_rgb.safetensors"}`,
/// or fewer), written by xtask.
pub const MANIFEST_URL: &str = "models/manifest.json";
/// The demo model's RGB discriminator (the reconstruction's perceptual term), when it ships.
pub const DISCRIMINATOR_URL: &str = "models/demo_d_rgb.safetensors";
/// The photo encoder trained for the demo model (the reconstruction's first guess), when it ships.
pub const ENCODER_URL: &str = "models/encoder.safetensors";

/// Which weights the generator has.
#[derive(Clone, Debug, PartialEq)]
pub enum Weights {
    Loading,
    /// Trained checkpoint (its size in bytes, and how many latent modes it carries).
    Trained(usize, usize),
    /// Deterministic random weights, and why.
    Random(String),
}

impl Weights {
    /// One line for the panel and the automation status.
    pub fn describe(&self) -> String {
        match self {
            Weights::Loading => format!("loading the trained demo model ({MODEL_URL})…"),
            Weights::Trained(n, 0) => format!("trained demo model ({:.1} MB)", *n as f64 / 1e6),
            Weights::Trained(n, k) => {
                format!(
                    "trained demo model ({:.1} MB; ψ truncates towards the nearest of {k} latent modes)",
                    *n as f64 / 1e6
                )
            }
            Weights::Random(why) => format!("untrained demo generator (random weights): {why}"),
        }
    }
}

/// The shipped demo model, if the build lists one, loaded onto `device`, with its bytes (the
/// reconstruction loads them again onto the autodiff device) and, where it ships, the bytes of
/// its RGB discriminator (or why they are missing).
async fn load_shipped(cfg: &GeneratorConfig, device: &Device) -> Result<Shipped, String> {
    let manifest: serde_json::Value =
        serde_json::from_slice(&fetch_bytes(MANIFEST_URL).await?).map_err(|e| format!("{MANIFEST_URL}: {e}"))?;
    if manifest.get("demo").is_none() {
        return Err("no trained model ships with this build".into());
    }
    let bytes = fetch_bytes(MODEL_URL).await?;
    // A checkpoint grown to finer detail planes, or extracted on another tet grid, brings its
    // own config (`texture_res`, `geometry_res`, `tet_res`).
    let cfg = config_with_saved_resolutions(&bytes, cfg);
    let (g, modes) = load_generator_and_modes(&bytes, &cfg, device)
        .map_err(|e| format!("{MODEL_URL} is not a demo checkpoint: {e}"))?;
    let disc = match manifest.get("demo_d") {
        Some(_) => fetch_bytes(DISCRIMINATOR_URL).await.map(Rc::new),
        None => Err("no discriminator ships with this build".into()),
    };
    let encoder = match manifest.get("encoder") {
        Some(_) => fetch_bytes(ENCODER_URL).await.and_then(|bytes| usable_encoder(bytes, &g)),
        None => Err("no photo encoder ships with this build".into()),
    };
    Ok(Shipped { generator: g, cfg, modes, bytes: Rc::new(bytes), discriminator: disc, encoder })
}

/// The encoder file's bytes if they load as an encoder for `g` (on the CPU, the weights then
/// dropped: a few MB), else why not, so a broken file is known when the model loads and a
/// reconstruction starts from the search of the model's subjects, saying why, in one stage.
fn usable_encoder(bytes: Vec<u8>, g: &Generator) -> Result<Rc<Vec<u8>>, String> {
    #[allow(deprecated)] // burn 0.22 marks NdArray deprecated in favour of flex; the project's CPU backend.
    let cpu = Device::ndarray();
    match load_encoder_for(&bytes, g, &cpu) {
        Ok(_) => Ok(Rc::new(bytes)),
        Err(e) => {
            web_sys::console::warn_1(&format!("{ENCODER_URL} cannot be used: {e}").into());
            Err(format!("{ENCODER_URL} cannot be used ({e})"))
        }
    }
}

/// Generate one avatar and drop it, while the model loads: the first use of each GPU kernel
/// compiles it (cubecl → WGSL → the browser's shader compiler), single tasks of up to ~0.8 s on
/// this project's software-GPU test machine that cannot be sliced. Done here, no generation the
/// user asks for pays them. A failure only means the first generation compiles.
///
/// Not on a `software` adapter: there new identities are generated in the reconstruction
/// worker on NdArray, and on SwiftShader this warm-up took 47 s (the bake's kernels 11 s, the
/// surface sizes' 21 s, the rest the generation): the model was ready 50 s after the page
/// loaded, without it 2.8 s (`tests/e2e/bench_generate.mjs`). New textures are computed in
/// the worker too; the first bake compiles its kernels when it runs (tasks of 0.2–0.4 s).
async fn warm_up(shipped: &Shipped, ctx: &BodyContext, cfg: &GeneratorConfig, device: &Device, software: bool) {
    let (zg, zt) = seed_latents(cfg, 0, 0, device);
    let styles = shipped.generator.styles_with(zg, zt, default_psi(shipped.modes.as_ref()), shipped.modes.as_ref());
    if software {
        // The page still maps every generation's seeds to its styles (for its texture field):
        // those kernels' compiles (a 0.3 s task) are made here.
        let mapped = Tensor::cat(vec![styles.geo.clone().sum(), styles.tex.clone().sum()], 0);
        if let Err(e) = getavatar_core::generator::readback::read_f32(mapped).await {
            web_sys::console::warn_1(&format!("warming the mapping's kernels up failed: {e}").into());
        }
        return;
    }
    if let Err(e) = generate_rigged_async(&shipped.generator, ctx, &styles, device).await {
        web_sys::console::warn_1(&format!("warming the generator's kernels up failed: {e}").into());
    }
    // The texture bake's batch shape (the downloads' first bake compiled 0.2–0.4 s tasks).
    let planes = shipped.generator.triplanes_async(&styles).await;
    if let Err(e) = warm_bake_kernels(&shipped.generator, &planes, &styles, device).await {
        web_sys::console::warn_1(&format!("warming the bake's kernels up failed: {e}").into());
    }
    // Other avatars' surface sizes than this one's (their field kernels differ by size class).
    if let Err(e) = warm_surface_kernels(&shipped.generator, ctx, &planes, &styles, device).await {
        web_sys::console::warn_1(&format!("warming the surface fields' kernels up failed: {e}").into());
    }
}

/// The files a reconstruction loads.
pub struct ModelFiles {
    /// The checkpoint's bytes (None: random weights).
    pub checkpoint: Option<Rc<Vec<u8>>>,
    /// The RGB discriminator's bytes (the perceptual term) and the photo encoder's (the first
    /// guess), or why there are none.
    pub discriminator: Result<Rc<Vec<u8>>, String>,
    pub encoder: Result<Rc<Vec<u8>>, String>,
    pub cfg: GeneratorConfig,
}

/// Colours of a texture-field query, or why it failed.
type TextureColours = Result<Vec<glam::Vec3>, String>;
/// A finished bake: the texture field it was baked from (which avatar and colours it
/// belongs to) and the texture, or why it failed.
type Bake = (Rc<TextureField>, Result<Baked, String>);

/// A baked texture, its milliseconds, where its texture-field queries ran and its stages' times.
pub struct Baked {
    pub texture: BakedTexture,
    pub millis: f64,
    pub on: &'static str,
    pub detail: String,
}

/// A fetched checkpoint: the generator, its latent modes (if any), its bytes, and the
/// discriminator's bytes (or why there are none).
struct Shipped {
    generator: Generator,
    /// The config the file was loaded under (the preset, or the file's own texture planes).
    cfg: GeneratorConfig,
    modes: Option<LatentModes>,
    bytes: Rc<Vec<u8>>,
    discriminator: Result<Rc<Vec<u8>>, String>,
    encoder: Result<Rc<Vec<u8>>, String>,
}

type Job = ((u64, u64), Option<f32>, Option<RiggedAvatar>, Compute, Vec<f32>, eframe::egui::Context);

/// What the engine prepares at start: the shipped checkpoint (or why none) and the body's
/// context (None without a body model).
type Loaded = (Result<Shipped, String>, Option<Rc<BodyContext>>);

/// Outcome of a background generation.
pub struct Finished {
    pub rigged: RiggedAvatar,
    /// This avatar's texture field, for per-pixel queries.
    pub field: Rc<TextureField>,
    pub millis: f64,
    /// Its stages: host milliseconds, waits on the GPU, read-backs (`core::profile`).
    pub stages: Option<getavatar_core::util::profile::StageProfile>,
    /// (geometry, texture) seeds of this result.
    pub seeds: (u64, u64),
    /// The truncation ψ it was generated with.
    pub psi: f32,
    /// Where it was generated ("the worker's CPU (burn NdArray)", "the page's WebGPU device").
    pub on: String,
}

pub struct GenEngine {
    device: Device,
    cfg: GeneratorConfig,
    generator: Rc<Generator>,
    /// The checkpoint's latent modes: ψ truncates towards the nearest one instead of w_avg.
    modes: Rc<Option<LatentModes>>,
    /// The checkpoint's bytes (None: random weights) and its discriminator's (or why none).
    checkpoint: Option<Rc<Vec<u8>>>,
    discriminator: Result<Rc<Vec<u8>>, String>,
    /// The photo encoder's bytes (or why none).
    encoder: Result<Rc<Vec<u8>>, String>,
    ctx: Option<Rc<BodyContext>>,
    slot: Rc<RefCell<Option<Result<Finished, String>>>>,
    /// The fetched checkpoint, parsed, and the body context (taken by [`GenEngine::poll`]).
    weights_slot: Rc<RefCell<Option<Loaded>>>,
    pub weights: Weights,
    texture_slot: Rc<RefCell<Option<TextureColours>>>,
    bake_slot: Rc<RefCell<Option<Bake>>>,
    /// A bake is running.
    pub baking: bool,
    /// A generation asked for while the weights were loading.
    pending: Option<Job>,
    /// The WebGPU adapter is a software one (a CPU): new identities are generated in the
    /// reconstruction worker on burn's NdArray, 6–10× faster there (docs/benchmarks.md).
    software: bool,
    /// Where texture-field colours are computed (bakes, the per-pixel view): `Auto` in the
    /// worker on a software adapter (automation `{"texture_device":…}`).
    pub texture_device: Compute,
    pub busy: bool,
    /// How the worker's warm-up had its body context ("read from the browser's cache …",
    /// "built … kept …"), or why it did not get ready ahead; empty before its answer.
    worker_body_context: Rc<RefCell<String>>,
    /// Repaints the page when something arrives that the status shows.
    repaint: eframe::egui::Context,
}

/// Compute passes cubecl records before it submits them to the queue (its default is 32). A
/// new identity issues ≈ 800 of them; each `queue.submit` crosses from wasm to the browser's
/// GPU process.
const WGPU_TASKS_PER_SUBMIT: usize = 256;

/// A generation's inputs: the page's generator, the styles it mapped, and where the worker
/// may do the work instead (the model's bytes; None: on the page).
struct Generation<'a> {
    g: &'a Generator,
    styles: &'a Styles,
    dev: &'a Device,
    cfg: &'a GeneratorConfig,
    worker: Option<&'a Rc<Vec<u8>>>,
    seeds: (u64, u64),
    psi: f32,
}

/// A generation's avatar, the triplanes where the page computed them, where it ran, and the
/// worker's stages when it ran there.
struct Made {
    rigged: RiggedAvatar,
    planes: Option<Triplanes>,
    on: &'static str,
    worker_stages: Option<Option<getavatar_core::util::profile::StageProfile>>,
}

impl Generation<'_> {
    /// New colours on `r`'s geometry: in the worker, else (or when it fails) on the page.
    async fn new_texture(&self, mut r: RiggedAvatar) -> Result<Made, ReadbackError> {
        let points = &r.canonical.mesh.attributes;
        let in_worker = match self.worker {
            Some(bytes) => {
                let field = WorkerField::Seeds { seeds: self.seeds, psi: self.psi };
                colours_in_worker(self.cfg, bytes, &field, None, points).await
            }
            None => Err(String::new()),
        };
        let (colors, planes, on) = match in_worker {
            Ok((colors, _)) => (colors, None, ON_WORKER),
            Err(why) => {
                fell_back("a new texture", &why);
                profile::stage("synthesis");
                let planes = self.g.triplanes_async(self.styles).await;
                profile::stage("colours");
                (recolor_async(self.g, &planes, self.styles, points, self.dev).await?, Some(planes), ON_PAGE)
            }
        };
        r.canonical.colors = colors;
        Ok(Made { rigged: r, planes, on, worker_stages: None })
    }

    /// A new identity, its bind pose at shape `betas` kept: in the worker, else (or when it
    /// fails) on the page.
    async fn new_identity(&self, ctx: &BodyContext, betas: &[f32]) -> Result<Made, ReadbackError> {
        let in_worker = match self.worker {
            Some(bytes) => match generate_in_worker(self.cfg, bytes, self.seeds, self.psi).await {
                Ok((arrays, _, stages)) => RiggedAvatar::from_arrays(arrays, ctx)
                    .map(|r| (r, stages))
                    .map_err(|e| format!("the worker's avatar: {e}")),
                Err(e) => Err(e),
            },
            None => Err(String::new()),
        };
        let (mut rigged, on, worker_stages) = match in_worker {
            Ok((r, stages)) => (r, ON_WORKER, Some(stages)),
            Err(why) => {
                fell_back("generating", &why);
                (generate_rigged_async(self.g, ctx, self.styles, self.dev).await?, ON_PAGE, None)
            }
        };
        rigged.keep_bind_pose_async(ctx, betas).await;
        Ok(Made { rigged, planes: None, on, worker_stages })
    }
}

impl GenEngine {
    /// Register egui's wgpu device with burn, build the `demo` generator and start fetching
    /// its trained weights and preparing `body`'s context (its template SDF: a second of work
    /// done in slices, `core::cooperative`); generations asked for before both are ready wait.
    pub fn new(
        rs: &egui_wgpu::RenderState,
        body: Option<BodyModel>,
        repaint: eframe::egui::Context,
    ) -> Result<Self, String> {
        let setup = WgpuSetup {
            instance: rs.instance.clone(),
            adapter: rs.adapter.clone(),
            device: rs.device.clone(),
            queue: rs.queue.clone(),
            backend: rs.adapter.get_info().backend,
        };
        let device = Device::wgpu_options()
            .tasks_max(WGPU_TASKS_PER_SUBMIT)
            .setup(setup)
            .init()
            .map_err(|e| format!("burn cannot use the WebGPU device: {e:?}"))?;
        let software = rs.adapter.get_info().device_type == egui_wgpu::wgpu::DeviceType::Cpu;
        let cfg = GeneratorConfig::demo();
        let generator = Rc::new(Generator::new(&cfg, 0, &device));
        let weights_slot = Rc::new(RefCell::new(None));
        {
            let (slot, cfg, device, repaint) = (weights_slot.clone(), cfg.clone(), device.clone(), repaint.clone());
            wasm_bindgen_futures::spawn_local(async move {
                let now = crate::platform::now_ms;
                let t = [now(), 0.0, 0.0, 0.0];
                let loaded = load_shipped(&cfg, &device).await;
                let t = [t[0], now(), 0.0, 0.0];
                // The shipped file's config where it brings its own resolutions (its tet grid).
                let cfg = loaded.as_ref().map_or(&cfg, |s| &s.cfg);
                let ctx = match body {
                    Some(b) => Some(Rc::new(BodyContext::new_async(b, cfg).await)),
                    None => None,
                };
                let t = [t[0], t[1], now(), 0.0];
                if let (Ok(shipped), Some(ctx)) = (&loaded, &ctx) {
                    warm_up(shipped, ctx, &shipped.cfg, &device, software).await;
                }
                let t = [t[0], t[1], t[2], now()];
                web_sys::console::info_1(
                    &format!(
                        "the model: fetched and loaded in {:.0} ms, the body's context {:.0} ms, kernels warmed up {:.0} ms",
                        t[1] - t[0],
                        t[2] - t[1],
                        t[3] - t[2]
                    )
                    .into(),
                );
                *slot.borrow_mut() = Some((loaded, ctx));
                repaint.request_repaint();
            });
        }
        Ok(Self {
            device,
            cfg,
            generator,
            modes: Rc::new(None),
            checkpoint: None,
            discriminator: Err("the model is loading".into()),
            encoder: Err("the model is loading".into()),
            ctx: None,
            slot: Rc::new(RefCell::new(None)),
            weights_slot,
            weights: Weights::Loading,
            texture_slot: Rc::new(RefCell::new(None)),
            bake_slot: Rc::new(RefCell::new(None)),
            baking: false,
            pending: None,
            busy: false,
            software,
            texture_device: Compute::Auto,
            worker_body_context: Rc::default(),
            repaint,
        })
    }

    /// Start generating (full, or texture only on `keep`'s geometry; a new identity where
    /// `compute` says: `Cpu` in the reconstruction worker, `WebGpu` on the page, `Auto` the
    /// first on a software adapter). The result arrives via [`GenEngine::poll`], its bind pose
    /// at shape `betas` (the app's) computed ahead for the viewer's upload.
    pub fn start(
        &mut self,
        seeds: (u64, u64),
        psi: Option<f32>,
        keep: Option<RiggedAvatar>,
        compute: Compute,
        betas: Vec<f32>,
        repaint: eframe::egui::Context,
    ) {
        if self.busy {
            return;
        }
        if self.weights == Weights::Loading {
            self.pending = Some((seeds, psi, keep, compute, betas, repaint));
            self.busy = true;
            return;
        }
        let Some(ctx) = self.ctx.clone() else {
            *self.slot.borrow_mut() = Some(Err("no body model: nothing to generate on".into()));
            return;
        };
        self.busy = true;
        let (g, dev, cfg, slot) = (self.generator.clone(), self.device.clone(), self.cfg.clone(), self.slot.clone());
        // By default a new identity is generated in the reconstruction worker on the CPU on a
        // software adapter (with the trained model; random weights stay on the page).
        let in_worker = match compute {
            Compute::Auto => self.software,
            Compute::Cpu => true,
            Compute::WebGpu => false,
        };
        let worker = self.checkpoint.clone().filter(|_| in_worker);
        let modes = self.modes.clone();
        // No ψ from the user: the loaded model's default (`generator::default_psi`).
        let psi = psi.unwrap_or_else(|| default_psi(modes.as_ref().as_ref()));
        wasm_bindgen_futures::spawn_local(async move {
            let t0 = crate::platform::now_ms();
            // Not in the frame that asked: the mapping network's launches are a slice of their own.
            crate::task::yield_to_browser().await;
            profile::start(crate::platform::now_ms);
            profile::stage("mapping");
            let (zg, zt) = seed_latents(&cfg, seeds.0, seeds.1, &dev);
            let styles = g.styles_with(zg, zt, psi, modes.as_ref().as_ref());
            crate::task::checkpoint().await;
            let job = Generation { g: &g, styles: &styles, dev: &dev, cfg: &cfg, worker: worker.as_ref(), seeds, psi };
            let generated = match keep {
                Some(r) => job.new_texture(r).await,
                None => job.new_identity(&ctx, &betas).await,
            };
            let page_stages = profile::finish();
            let result = match generated {
                Err(e) => Err(format!("generation failed: {e}")),
                Ok(m) if m.rigged.canonical.mesh.faces.is_empty() => {
                    Err("the generator produced an empty surface".to_string())
                }
                Ok(Made { rigged, planes, on, worker_stages }) => {
                    // Generated in the worker: its stages (mapping to rigging) stand for the page's.
                    let stages = worker_stages.unwrap_or(page_stages);
                    let field = Rc::new(TextureField::generated(g, styles, planes, seeds, psi));
                    let millis = crate::platform::now_ms() - t0;
                    Ok(Finished { rigged, field, millis, stages, seeds, psi, on: on.to_string() })
                }
            };
            *slot.borrow_mut() = Some(result);
            repaint.request_repaint();
        });
    }

    /// The finished generation, if any (once). Also installs fetched weights and starts a
    /// generation that waited for them.
    pub fn poll(&mut self) -> Option<Result<Finished, String>> {
        let fetched = self.weights_slot.borrow_mut().take();
        if let Some((w, ctx)) = fetched {
            self.ctx = ctx;
            self.weights = match w {
                Ok(shipped) => {
                    self.generator = Rc::new(shipped.generator);
                    self.cfg = shipped.cfg;
                    let k = shipped.modes.as_ref().map_or(0, LatentModes::count);
                    self.modes = Rc::new(shipped.modes);
                    let n = shipped.bytes.len();
                    self.checkpoint = Some(shipped.bytes);
                    self.discriminator = shipped.discriminator;
                    self.encoder = shipped.encoder;
                    if self.software {
                        self.warm_worker();
                    }
                    Weights::Trained(n, k)
                }
                Err(e) => {
                    self.discriminator = Err("no trained model ships with this build".into());
                    self.encoder = Err("no trained model ships with this build".into());
                    Weights::Random(e)
                }
            };
            if let Some((seeds, psi, keep, compute, betas, repaint)) = self.pending.take() {
                self.busy = false;
                self.start(seeds, psi, keep, compute, betas, repaint);
            }
        }
        let r = self.slot.borrow_mut().take();
        if r.is_some() {
            self.busy = false;
        }
        r
    }

    /// Query the texture field of `field` at canonical points (the per-pixel RGB of the
    /// paper's renderer; in the worker on a software adapter); the colours arrive via
    /// [`GenEngine::poll_texture`].
    pub fn query_texture(&mut self, field: Rc<TextureField>, points: Vec<glam::Vec3>, repaint: eframe::egui::Context) {
        let (dev, slot, worker) = (self.device.clone(), self.texture_slot.clone(), self.worker_files());
        wasm_bindgen_futures::spawn_local(async move {
            let colors = field
                .colours(&points, &dev, worker.as_ref().map(|(c, b)| (c, b)))
                .await
                .map(|(c, _)| c)
                .map_err(|e| format!("texture query failed: {e}"));
            *slot.borrow_mut() = Some(colors);
            repaint.request_repaint();
        });
    }

    /// Colours of the last [`GenEngine::query_texture`] (or why it failed), once.
    pub fn poll_texture(&mut self) -> Option<Result<Vec<glam::Vec3>, String>> {
        self.texture_slot.borrow_mut().take()
    }

    /// Start the reconstruction worker while the page is idle and have it get ready for the
    /// first Generate (on a software adapter Generate runs there; a fresh worker's first took
    /// about 5 s, 3.2 s of it the canonical pose's posed grid). Work asked for meanwhile waits in
    /// the worker behind it; a failure only costs the first Generate its head start.
    fn warm_worker(&self) {
        let (Some(checkpoint), cfg) = (self.checkpoint.clone(), self.cfg.clone()) else { return };
        let (said, repaint) = (self.worker_body_context.clone(), self.repaint.clone());
        wasm_bindgen_futures::spawn_local(async move {
            *said.borrow_mut() = match warm_worker(&cfg, &checkpoint).await {
                Ok((ms, how)) => {
                    web_sys::console::info_1(&format!("the worker is ready for Generate ({ms:.0} ms)").into());
                    how
                }
                Err(e) => {
                    web_sys::console::warn_1(&format!("the worker did not get ready ahead: {e}").into());
                    format!("the worker did not get ready ahead: {e}")
                }
            };
            repaint.request_repaint();
        });
    }

    /// How the worker's warm-up had its body context, or why it did not get ready ahead
    /// (empty before its answer, or where no warm-up runs: a hardware adapter).
    pub fn worker_body_context(&self) -> String {
        self.worker_body_context.borrow().clone()
    }

    /// The model's config and file where the worker computes texture-field colours (by
    /// default on a software adapter, with a trained model); None: the page does.
    fn worker_files(&self) -> Option<(GeneratorConfig, Rc<Vec<u8>>)> {
        let in_worker = match self.texture_device {
            Compute::Auto => self.software,
            Compute::Cpu => true,
            Compute::WebGpu => false,
        };
        self.checkpoint.clone().filter(|_| in_worker).map(|b| (self.cfg.clone(), b))
    }

    /// Bake `rigged`'s texture field (`field`) into a `res²` atlas image for the downloads:
    /// the atlas and its texels here, the texture-field queries in the worker on a software
    /// adapter (else on the WebGPU device), the photo's projection blended in here; the
    /// result (and where the queries ran) arrives via [`GenEngine::poll_bake`].
    pub fn bake(&mut self, field: Rc<TextureField>, rigged: RiggedAvatar, res: usize, repaint: eframe::egui::Context) {
        let Some(ctx) = self.ctx.clone() else {
            *self.bake_slot.borrow_mut() = Some((field, Err("the body context is not ready".into())));
            return;
        };
        let (dev, slot, worker) = (self.device.clone(), self.bake_slot.clone(), self.worker_files());
        self.baking = true;
        wasm_bindgen_futures::spawn_local(async move {
            let t0 = crate::platform::now_ms();
            let baked = async {
                let now = crate::platform::now_ms;
                let plan = rigged.bake_plan_async(&ctx, res).await.map_err(|e| e.to_string())?;
                let t1 = now();
                let (colors, on) = field.colours(&plan.points, &dev, worker.as_ref().map(|(c, b)| (c, b))).await?;
                let t2 = now();
                let photo = field.projection.as_deref().map(|p| (&p.projection, &p.photo.view.body));
                let b = rigged.bake_finish_async(&ctx, plan, colors, photo).await.map_err(|e| e.to_string())?;
                let (t3, n) = (now(), b.covered);
                let detail = format!(
                    "atlas and texels {:.0} ms, {n} texture-field queries {:.0} ms, image {:.0} ms",
                    t1 - t0,
                    t2 - t1,
                    t3 - t2
                );
                Ok::<_, String>(Baked { texture: b, millis: t3 - t0, on, detail })
            }
            .await;
            *slot.borrow_mut() = Some((field, baked.map_err(|e| format!("texture bake failed: {e}"))));
            repaint.request_repaint();
        });
    }

    /// The last [`GenEngine::bake`]'s texture (or why it failed) with the field it was
    /// baked from, once.
    pub fn poll_bake(&mut self) -> Option<Bake> {
        let r = self.bake_slot.borrow_mut().take();
        if r.is_some() {
            self.baking = false;
        }
        r
    }

    /// burn's device on egui's WebGPU device.
    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn context(&self) -> Option<&BodyContext> {
        self.ctx.as_deref()
    }

    /// The body context (prepared with the weights; an error while they load or without a
    /// body model).
    pub fn body_context(&self) -> Result<Rc<BodyContext>, String> {
        match (&self.weights, &self.ctx) {
            (Weights::Loading, _) => Err("the model is still loading".into()),
            (_, Some(c)) => Ok(c.clone()),
            (_, None) => Err("no body model is loaded".into()),
        }
    }

    /// What a reconstruction loads (an error while the model loads).
    pub fn model_files(&self) -> Result<ModelFiles, String> {
        match &self.weights {
            Weights::Loading => Err("the model is still loading".into()),
            Weights::Trained(..) | Weights::Random(_) => Ok(ModelFiles {
                checkpoint: self.checkpoint.clone(),
                discriminator: self.discriminator.clone(),
                encoder: self.encoder.clone(),
                cfg: self.cfg.clone(),
            }),
        }
    }
}
