//! `trainer bench generator`: timings of the generator stages, measured in one run, printed as a table
//! with ratios (no assertions: performance claims live here, not in tests).

use std::time::Instant;

use std::path::Path;

use anyhow::{bail, Context, Result};
use getavatar_core::io::dataset::Dataset;
use getavatar_core::render::diff::avatar::PosedGridCache;
use serde::{Deserialize, Serialize};

use crate::backend::device_for;
use crate::train::{train_step, RunConfig, ScanPools, State, StepInputs};
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::pose_body;
use getavatar_core::burn::module::Module;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{generate_avatar, seed_latents, BodyContext, Generator};
use getavatar_core::generator::readback::{block_on_ready, read_f32_now};
use getavatar_core::generator::rigging::generate_rigged_async;
use getavatar_core::geometry::{InverseSkinning, PosedGrid};
use getavatar_core::render::camera::OrbitCamera;
use getavatar_core::render::rasterize::render_views;
use getavatar_core::util::profile::StageProfile;

fn secs<T>(f: impl FnOnce() -> T) -> (T, f64) {
    let t = Instant::now();
    let v = f();
    (v, t.elapsed().as_secs_f64())
}

pub fn bench(configs: &[String], repeats: usize, backend: &str) -> Result<()> {
    let device = device_for(backend)?;
    let model = BodyModel::default_body()?;
    let lib = PoseLibrary::builtin();
    let poses = ["standing", "walking", "sitting", "arms_up"];
    let on = crate::backend::opened_adapter().map_or("CPU".to_string(), |a| a.describe());
    println!(
        "backend: {backend} for the networks, on {on}; {} CPU threads available",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!(
        "{:<6} {:>10} {:>10} {:>10} {:>10} {:>10} {:>10} {:>8} {:>10} {:>12} {:>12} {:>8}",
        "config",
        "setup s",
        "gen s",
        "extract s",
        "grid s",
        "grid-all s",
        "skip",
        "r512 s",
        "r1024 s",
        "exact/pose s",
        "fast/pose s",
        "ratio"
    );
    let mut stage_tables = Vec::new();
    let mut kept_contexts = Vec::new();
    for name in configs {
        let cfg = GeneratorConfig::preset(name).with_context(|| format!("unknown config `{name}`"))?;
        let ((ctx, g), setup) = secs(|| (BodyContext::new(model.clone(), &cfg), Generator::new(&cfg, 0, &device)));
        let (zg, zt) = seed_latents(&cfg, 1, 2, &device);
        let s = g.styles(zg, zt, 0.7);
        let params: Vec<_> = poses.iter().map(|p| lib.params(p, &[])).collect::<Result<_, _>>()?;
        if backend == "wgpu" {
            // Compile the kernels first: `gen` and `exact` are steady-state figures.
            generate_avatar(&g, &ctx, &s, &params[0], &device)?;
        }
        // Network only: styles → triplanes, read back to force execution.
        let (gen_read, gen) = secs(|| {
            let p = g.triplanes(&s);
            read_f32_now(p.geometry).map(|_| ())
        });
        gen_read?;
        let (avatar, exact_total) = secs(|| -> Result<_> {
            let mut last = None;
            for _ in 0..repeats {
                for p in &params {
                    last = Some(generate_avatar(&g, &ctx, &s, p, &device)?);
                }
            }
            Ok(last)
        });
        let exact = exact_total / (repeats * params.len()) as f64;
        let avatar = avatar?.context("no avatar")?;
        let extract = (exact - gen).max(0.0);
        // The posed grid (inverse skinning of every tet-grid vertex) with far vertices skipped,
        // and with every vertex un-warped.
        let invs: Vec<InverseSkinning> =
            params.iter().map(|p| InverseSkinning::new(&model, &pose_body(&model, p), &ctx.canonical)).collect();
        let per_pose = |far: Option<f32>| {
            secs(|| {
                for _ in 0..repeats {
                    for inv in &invs {
                        let _ = match far {
                            None => PosedGrid::new(&ctx, inv),
                            Some(f) => PosedGrid::with_far(&ctx, inv, f),
                        };
                    }
                }
            })
            .1 / (repeats * invs.len()) as f64
        };
        let (grid, grid_all) = (per_pose(None), per_pose(Some(f32::INFINITY)));
        let cam = OrbitCamera::default();
        let vp = cam.projection_gl(1.0) * cam.world_to_camera();
        let m = &avatar.mesh;
        let (_, r512) = secs(|| render_views(&m.vertices, &m.faces, &avatar.normals, &avatar.colors, vp, 512, 1));
        let (_, r1024) = secs(|| render_views(&m.vertices, &m.faces, &avatar.normals, &avatar.colors, vp, 1024, 1));
        let rigged = block_on_ready(generate_rigged_async(&g, &ctx, &s, &device))?;
        // The app's new identity (canonical generation + rigging) by stage, kernels warm: seeds
        // 3/4 as the app runs it (host and GPU pipelined), the same again with the device
        // synced at each stage's end (each stage's own GPU time; the pipelined run charges it
        // to the next read-back's wait), and seeds 5/6 (another new identity: kernels compiled
        // or tuned for the first one's shapes only show up here).
        use getavatar_core::util::profile::dispatch_count;
        let before = dispatch_count::by_kernel();
        let stages = profile_identity((&g, &cfg, &ctx), &device, (3, 4), false)?;
        // The new identity's launches per kernel: the counts now minus those before it.
        let kernels: Vec<(&str, u64)> = dispatch_count::by_kernel()
            .into_iter()
            .map(|(k, n)| (k, n - before.iter().find(|b| b.0 == k).map_or(0, |b| b.1)))
            .filter(|(_, n)| *n > 0)
            .collect();
        let synced = profile_identity((&g, &cfg, &ctx), &device, (3, 4), true)?;
        let another = profile_identity((&g, &cfg, &ctx), &device, (5, 6), false)?;
        stage_tables.push((name.clone(), [stages, synced, another], g.num_params(), kernels));
        let (_, fast_total) = secs(|| {
            for _ in 0..repeats {
                for p in &params {
                    let posed = pose_body(&model, p);
                    let _ = rigged.repose(&ctx, &posed);
                }
            }
        });
        let fast = fast_total / (repeats * params.len()) as f64;
        kept_contexts.push((name.clone(), kept_context(&model, &cfg)?));
        println!(
            "{:<6} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>7.1}× {:>10.3} {:>10.3} {:>12.3} {:>12.4} {:>7.0}×",
            name,
            setup,
            gen,
            extract,
            grid,
            grid_all,
            grid_all / grid.max(1e-9),
            r512,
            r1024,
            exact,
            fast,
            exact / fast.max(1e-9)
        );
    }
    println!("gen = mapping + triplane synthesis; extract = exact per-pose path minus gen (inverse skinning, decoders, DMTet, normal field, colours);");
    println!("gen/extract/exact run the networks on the backend above (grid inverse skinning and DMTet topology on the CPU); on wgpu after one untimed generation (kernels compiled);");
    println!("grid = posed grid per pose (inverse skinning of the tet grid, part of extract) skipping vertices far from the body; grid-all = un-warping every vertex; skip = grid-all / grid;");
    println!("r512/r1024 = CPU reference rasteriser (RGB+normal+mask); ratio = exact per-frame path / fast re-pose path (LBS of the rigged canonical avatar).");
    println!("\nbody context: built = template SDF, tet grid and the canonical pose's posed grid made in the process; read = the same from the file an earlier command kept (`geometry::context_cache`, tet grid rebuilt beside the read), checked bit for bit");
    for (name, (built, read)) in kept_contexts {
        println!("{name:<6} built {built:.3} s, read {read:.3} s: {:.1}× faster", built / read.max(1e-9));
    }
    for (name, [stages, synced, another], num_params, mut kernels) in stage_tables {
        println!("\n`{name}`: the generator has {num_params} parameters ({:.1} MB as f32)", num_params as f64 * 4e-6);
        println!("new identity (canonical generation + rigging, seeds 3/4), `{name}`, {backend}: host ms, waits on read-backs, read-backs");
        print!("{}", stages.table());
        println!("the same, the device synced at each stage's end (GPU wait = the stage's own GPU work; host and GPU no longer overlap):");
        print!("{}", synced.table());
        println!("another new identity (seeds 5/6), pipelined:");
        print!("{}", another.table());
        if !kernels.is_empty() {
            kernels.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
            println!("its GPU launches by kernel (the 12 most launched of {}):", kernels.len());
            for (k, n) in kernels.iter().take(12) {
                println!("{n:>6} × {k}");
            }
        }
    }
    Ok(())
}

/// One new identity (canonical generation + rigging, ψ 0.7) recorded stage by stage; when
/// `synced`, the device is synced at each stage's end (a failed sync fails the call).
fn profile_identity(
    (g, cfg, ctx): (&Generator, &GeneratorConfig, &BodyContext),
    device: &Device,
    (seed_geo, seed_tex): (u64, u64),
    synced: bool,
) -> Result<StageProfile> {
    let sync_error = std::rc::Rc::new(std::cell::RefCell::new(None));
    if synced {
        let (device, error) = (device.clone(), sync_error.clone());
        getavatar_core::util::profile::start_synced(
            clock_ms,
            Box::new(move || {
                if let Err(e) = device.sync() {
                    error.borrow_mut().get_or_insert(format!("{e:?}"));
                }
            }),
        );
    } else {
        getavatar_core::util::profile::start(clock_ms);
    }
    getavatar_core::util::profile::stage("mapping");
    let (zg, zt) = seed_latents(cfg, seed_geo, seed_tex, device);
    let styles = g.styles(zg, zt, 0.7);
    let run = block_on_ready(generate_rigged_async(g, ctx, &styles, device));
    let stages = getavatar_core::util::profile::finish().context("the stage recording was lost")?;
    run?;
    if let Some(e) = sync_error.borrow_mut().take() {
        bail!("waiting for the device failed: {e}");
    }
    Ok(stages)
}

/// Milliseconds since the first call (the stage recorder's clock).
pub(crate) fn clock_ms() -> f64 {
    static T0: std::sync::OnceLock<std::time::Instant> = std::sync::OnceLock::new();
    T0.get_or_init(std::time::Instant::now).elapsed().as_secs_f64() * 1000.0
}

/// What `trainer bench train` measures.
pub struct TrainBenchArgs {
    pub configs: Vec<String>,
    pub backends: Vec<String>,
    pub resolutions: Vec<usize>,
    pub batch: usize,
    pub steps: usize,
    /// Where the benchmark's small synthetic dataset is made (kept for re-runs).
    pub work: std::path::PathBuf,
}

/// One measured case, as the child process reports it.
#[derive(serde::Serialize, serde::Deserialize)]
pub struct CaseReport {
    pub timings: StepTimings,
    /// Peak resident memory of the process (VmHWM), MiB; lavapipe's "GPU" memory is host
    /// memory, so this covers both backends; a real GPU's memory is not in it.
    pub peak_mib: Option<f64>,
    /// The wgpu adapter the case ran on (`Adapter::describe`), none on NdArray.
    #[serde(default)]
    pub adapter: Option<String>,
}

const CASE_TAG: &str = "GETAVATAR_BENCH_CASE ";

/// Peak resident set size of this process, MiB (Linux).
fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

/// The child side: time one case and print its report (one process per case, so the peak
/// memory is that case's).
pub fn train_case(data: &std::path::Path, config: &str, backend: &str, batch: usize, steps: usize) -> Result<()> {
    let timings = time_steps(data, config, backend, batch, steps)?;
    let adapter = crate::backend::opened_adapter().map(|a| a.describe());
    let r = CaseReport { timings, peak_mib: peak_rss_mib(), adapter };
    println!("{CASE_TAG}{}", serde_json::to_string(&r)?);
    Ok(())
}

/// Training speed per config, backend and render resolution: seconds per step and per kimg
/// (lazy R1 amortised over its interval), peak memory, and ratios (wgpu / NdArray, each
/// resolution / the smallest), measured in one run.
pub fn bench_train(a: &TrainBenchArgs) -> Result<()> {
    anyhow::ensure!(a.batch >= 1 && a.steps >= 1, "--batch and --steps must be at least 1");
    anyhow::ensure!(!a.resolutions.is_empty(), "--res needs at least one resolution");
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let scans = a.work.join("scans");
    crate::synth_scans::synth_scans(&crate::synth_scans::SynthArgs {
        out: scans.clone(),
        count: 4,
        seed: 7,
        threads,
        texture_size: 256,
        pose: None,
    })?;
    for &res in &a.resolutions {
        crate::prepare::prepare(&crate::prepare::PrepareArgs {
            scans: scans.clone(),
            out: a.work.join(format!("ds{res}")),
            views: 4,
            res,
            ss: 2,
            seed: 7,
            threads,
            smpl_dir: None,
            limit: None,
        })?;
    }
    let exe = std::env::current_exe().context("locating the trainer executable")?;
    let r1_every = 16.0;
    let mut rows: Vec<(String, String, usize, CaseReport)> = Vec::new();
    for config in &a.configs {
        GeneratorConfig::preset(config).with_context(|| format!("unknown config `{config}`"))?;
        for backend in &a.backends {
            for &res in &a.resolutions {
                eprintln!("bench train: {config} on {backend} at {res}² …");
                let out = std::process::Command::new(&exe)
                    .args(["bench-train-case", "--data"])
                    .arg(a.work.join(format!("ds{res}")))
                    .args(["--config", config, "--backend", backend])
                    .args(["--batch", &a.batch.to_string(), "--steps", &a.steps.to_string()])
                    .stderr(std::process::Stdio::inherit())
                    .output()
                    .context("running a benchmark case")?;
                let text = String::from_utf8_lossy(&out.stdout);
                match text.lines().find_map(|l| l.strip_prefix(CASE_TAG)) {
                    Some(json) if out.status.success() => {
                        let r: CaseReport = serde_json::from_str(json)?;
                        // Each case as it finishes, so a run cut short still reports.
                        eprintln!(
                            "bench train: {config} on {backend} at {res}²: {:.2} s/step, R1 step {:.2} s, peak {} MiB",
                            r.timings.step_s,
                            r.timings.r1_step_s,
                            r.peak_mib.map_or("-".into(), |m| format!("{m:.0}"))
                        );
                        rows.push((config.clone(), backend.clone(), res, r))
                    }
                    _ => eprintln!("bench train: {config} on {backend} at {res}² failed ({}); skipped", out.status),
                }
            }
        }
    }
    println!("training benchmark: batch {}, {} timed steps per case, {threads} CPU threads", a.batch, a.steps);
    println!(
        "{:<6} {:<7} {:>5} {:>9} {:>9} {:>10} {:>9} {:>10} {:>9} {:>9} {:>10}",
        "config",
        "backend",
        "res",
        "first s",
        "step s",
        "R1 step s",
        "s/kimg",
        "peak MiB",
        "vs ndarr",
        "vs res0",
        "disp/step"
    );
    let per_kimg = |r: &CaseReport| {
        let t = &r.timings;
        (t.step_s + (t.r1_step_s - t.step_s).max(0.0) / r1_every) * 1000.0 / a.batch as f64
    };
    for (config, backend, res, r) in &rows {
        let find = |b: &str, rr: usize| rows.iter().find(|x| &x.0 == config && x.1 == b && x.2 == rr).map(|x| &x.3);
        let vs_nd =
            find("ndarray", *res).map_or("-".to_string(), |n| format!("{:.2}×", r.timings.step_s / n.timings.step_s));
        let vs_res = find(backend, a.resolutions[0])
            .map_or("-".to_string(), |n| format!("{:.2}×", r.timings.step_s / n.timings.step_s));
        println!(
            "{:<6} {:<7} {:>5} {:>9.2} {:>9.2} {:>10.2} {:>9.0} {:>10} {:>9} {:>9} {:>10.0}",
            config,
            backend,
            res,
            r.timings.first_step_s,
            r.timings.step_s,
            r.timings.r1_step_s,
            per_kimg(r),
            r.peak_mib.map_or("-".into(), |m| format!("{m:.0}")),
            vs_nd,
            vs_res,
            r.timings.dispatches_per_step
        );
    }
    println!("first = warm-up step (R1, tet-grid inverse skinning, kernel compilation); step = mean plain step; s/kimg = (step + (R1 step − step)/16) · 1000/batch;");
    let mut adapters: Vec<&str> = rows.iter().filter_map(|r| r.3.adapter.as_deref()).collect();
    adapters.dedup();
    for adapter in adapters {
        println!("wgpu adapter: {adapter}");
    }
    println!("peak = the case process's peak resident memory; vs ndarr = step time / NdArray's at the same config and resolution; vs res0 = / the first resolution's;");
    println!("disp/step = GPU kernel launches per plain step (cubecl's launch observer; 0 on NdArray).");
    Ok(())
}

/// Timings of a few training steps of a fresh run (the training benchmark's measurement).
#[derive(Debug, Serialize, Deserialize)]
pub struct StepTimings {
    /// First step: R1, inverse-skinning cache fill, kernel compilation.
    pub first_step_s: f64,
    /// Mean of the following plain steps (no R1).
    pub step_s: f64,
    /// One step with the lazy R1 penalty, after warm-up.
    pub r1_step_s: f64,
    /// GPU kernel launches per plain step (0 on NdArray).
    #[serde(default)]
    pub dispatches_per_step: f64,
}

/// Run `steps` plain steps (after one warm-up step) and one R1 step of a fresh run of `config`
/// on `ds` with `backend`.
pub fn time_steps(data: &Path, config: &str, backend: &str, batch: usize, steps: usize) -> Result<StepTimings> {
    let ds = Dataset::open(data).with_context(|| format!("opening dataset {}", data.display()))?;
    let gcfg = GeneratorConfig::preset(config).with_context(|| format!("unknown config `{config}`"))?;
    let rc = RunConfig::new(&ds, data, gcfg, batch, 10.0, 0);
    let base = device_for(backend)?;
    let (ad, plain) = (base.clone().autodiff(), base);
    let ctx = BodyContext::new(BodyModel::default_body()?, &rc.generator);
    let grids = PosedGridCache::default();
    let scans = ScanPools::default();
    let mut st = State::new(&rc, &ad, &plain);
    let inputs = StepInputs { ds: &ds, ctx: &ctx, grids: &grids, scans: &scans, rc: &rc, ad: &ad };
    let (next, first) = train_step(st, &inputs)?;
    st = next;
    let mut plain_s = Vec::new();
    let counting = getavatar_core::util::profile::dispatch_count::observe();
    let d0 = getavatar_core::util::profile::dispatch_count::total();
    for _ in 0..steps.max(1) {
        let (next, m) = train_step(st, &inputs)?;
        st = next;
        plain_s.push(m.seconds);
    }
    let dispatches = getavatar_core::util::profile::dispatch_count::total() - d0;
    drop(counting);
    st.step = rc.r1_every * (st.step / rc.r1_every + 1);
    let (_, r1) = train_step(st, &inputs)?;
    Ok(StepTimings {
        first_step_s: first.seconds,
        step_s: plain_s.iter().sum::<f64>() / plain_s.len() as f64,
        r1_step_s: r1.seconds,
        dispatches_per_step: dispatches as f64 / plain_s.len() as f64,
    })
}

/// Seconds to build `cfg`'s body context with its canonical grid, and to read it back from the
/// file a command keeps (`context_cache`'s bytes, written to a folder of its own first), which
/// must give the same template SDF and canonical grid to the bit.
fn kept_context(model: &BodyModel, cfg: &GeneratorConfig) -> Result<(f64, f64)> {
    use getavatar_core::geometry::context_cache::{build, file_name, from_bytes, to_bytes};
    let (built, t_built) = secs(|| build(model.clone(), cfg.template_res, cfg.tet_res));
    let dir = tempfile::tempdir().context("a folder for the body context's file")?;
    let path = dir.path().join(file_name(model, cfg.template_res, cfg.tet_res));
    crate::atomic::write_atomic(&path, &to_bytes(&built).map_err(anyhow::Error::msg)?)?;
    let (read, t_read) = secs(|| -> Result<BodyContext> {
        let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        from_bytes(model.clone(), &bytes, cfg.template_res, cfg.tet_res).map_err(anyhow::Error::msg)
    });
    let read = read?;
    let bits = |c: &BodyContext| {
        let grid = c.canonical_grid_made().map(|g| {
            let points = g.canonical.iter().flat_map(|p| p.to_array()).chain(g.template.iter().copied());
            points.map(f32::to_bits).chain(g.band.iter().copied()).collect::<Vec<u32>>()
        });
        (grid, c.template.values.iter().map(|v| v.to_bits()).collect::<Vec<u32>>())
    };
    if bits(&read) != bits(&built) || bits(&read).0.is_none() {
        bail!("the body context read back differs from the one built");
    }
    Ok((t_built, t_read))
}
