//! The Generate panel's engine: the generator running on burn's wgpu backend on the SAME
//! WebGPU device as egui. Generation runs as an async task (GPU readbacks are awaited); the
//! result is rigged to the body once, then re-posed by LBS every time the pose changes.

use std::cell::RefCell;
use std::rc::Rc;

use eframe::egui_wgpu;
use getavatar_core::body_model::BodyModel;
use getavatar_core::burn::tensor::wgpu::WgpuSetup;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::{
    generate_rigged_async, recolor_async, seed_latents, BodyContext, Generator, RiggedAvatar,
};
use getavatar_core::network::GeneratorConfig;

/// Outcome of a background generation.
pub struct Finished {
    pub rigged: RiggedAvatar,
    pub millis: f64,
    /// (geometry, texture) seeds of this result.
    pub seeds: (u64, u64),
}

pub struct GenEngine {
    device: Device,
    cfg: GeneratorConfig,
    generator: Rc<Generator>,
    ctx: Option<Rc<BodyContext>>,
    slot: Rc<RefCell<Option<Result<Finished, String>>>>,
    pub busy: bool,
}

impl GenEngine {
    /// Register egui's wgpu device with burn and build the generator (deterministic random
    /// weights of the `demo` config until a trained checkpoint ships).
    pub fn new(rs: &egui_wgpu::RenderState) -> Result<Self, String> {
        let setup = WgpuSetup {
            instance: rs.instance.clone(),
            adapter: rs.adapter.clone(),
            device: rs.device.clone(),
            queue: rs.queue.clone(),
            backend: rs.adapter.get_info().backend,
        };
        let device = Device::wgpu_options()
            .setup(setup)
            .init()
            .map_err(|e| format!("burn cannot use the WebGPU device: {e:?}"))?;
        let cfg = GeneratorConfig::demo();
        let generator = Rc::new(Generator::new(&cfg, 0, &device));
        Ok(Self { device, cfg, generator, ctx: None, slot: Rc::new(RefCell::new(None)), busy: false })
    }

    /// Start generating (full, or texture only on `keep`'s geometry). The result arrives via
    /// [`GenEngine::poll`].
    pub fn start(
        &mut self,
        body: &BodyModel,
        seeds: (u64, u64),
        psi: f32,
        keep: Option<RiggedAvatar>,
        repaint: eframe::egui::Context,
    ) {
        if self.busy {
            return;
        }
        let ctx = match &self.ctx {
            Some(c) => c.clone(),
            None => {
                let c = Rc::new(BodyContext::new(body.clone(), &self.cfg));
                self.ctx = Some(c.clone());
                c
            }
        };
        self.busy = true;
        let (g, dev, cfg, slot) = (self.generator.clone(), self.device.clone(), self.cfg.clone(), self.slot.clone());
        wasm_bindgen_futures::spawn_local(async move {
            let t0 = crate::web::now_ms();
            let (zg, zt) = seed_latents(&cfg, seeds.0, seeds.1, &dev);
            let styles = g.styles(zg, zt, psi);
            let rigged = match keep {
                Some(mut r) => {
                    let planes = g.triplanes(&styles);
                    r.canonical.colors = recolor_async(&g, &planes, &styles, &r.canonical.mesh.attributes, &dev).await;
                    r
                }
                None => generate_rigged_async(&g, &ctx, &styles, &dev).await,
            };
            let result = if rigged.canonical.mesh.faces.is_empty() {
                Err("the generator produced an empty surface".to_string())
            } else {
                Ok(Finished { rigged, millis: crate::web::now_ms() - t0, seeds })
            };
            *slot.borrow_mut() = Some(result);
            repaint.request_repaint();
        });
    }

    /// The finished generation, if any (once).
    pub fn poll(&mut self) -> Option<Result<Finished, String>> {
        let r = self.slot.borrow_mut().take();
        if r.is_some() {
            self.busy = false;
        }
        r
    }

    pub fn context(&self) -> Option<&BodyContext> {
        self.ctx.as_deref()
    }
}
