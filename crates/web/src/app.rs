//! The egui application: state, panels and the per-frame flow
//! (commands → pose the body → upload → render → show → publish status).

use eframe::egui;
use eframe::egui_wgpu;
use glam::Vec3;

use getavatar_core::body_model::{BodyModel, JOINT_NAMES, NUM_JOINTS};
use getavatar_core::colour::linear_to_srgb;
use getavatar_core::gltf_export::{write_glb, ExportMesh};
use getavatar_core::pose_library::{PoseLibrary, BUILTIN_POSE_NAMES};
use getavatar_core::skinning::{pose_body, vertex_normals, BodyParams};
use getavatar_core::OrbitCamera;

use std::rc::Rc;

use getavatar_core::generator::default_psi;
use getavatar_core::rigging::RiggedAvatar;

use crate::automation::{Action, GenerateArgs, Status, ViewMode, RESOLUTIONS};
use crate::generate::{GenEngine, TextureField};
use crate::viewer::{bone_transforms, Vertex, Viewer};
use crate::web;

/// Linear RGB albedo of the untextured body.
const SKIN: Vec3 = Vec3::new(0.62, 0.42, 0.32);

pub struct GetAvatarApp {
    body: Option<BodyModel>,
    poses: PoseLibrary,
    params: BodyParams,
    pose_name: String,
    camera: OrbitCamera,
    view: ViewMode,
    res: u32,
    continuous: bool,
    edit_joint: usize,
    viewer: Option<Viewer>,
    /// Mesh must be re-posed (bones for a rigged avatar, vertices for the body) and uploaded.
    mesh_dirty: bool,
    /// The avatar's canonical mesh on the GPU is stale (new avatar, new texture, toggled).
    avatar_dirty: bool,
    /// Viewport must be re-rendered.
    render_dirty: bool,
    status: Status,
    frame_times: std::collections::VecDeque<f64>,
    messages: Vec<String>,
    /// The generator on the shared WebGPU device (None if it could not start).
    engine: Option<GenEngine>,
    rigged: Option<RiggedAvatar>,
    /// The shown avatar's texture field (styles, triplanes) for per-pixel queries.
    field: Option<Rc<TextureField>>,
    /// Per-pixel texture view: the finished image, whether it shows the current frame, the
    /// frame counter it belongs to, and the job in flight.
    texture_image: Option<egui::TextureHandle>,
    texture_valid: bool,
    texture_epoch: u64,
    texture_job: Option<TextureJob>,
    /// The frame whose canonical-coordinate readback failed: not retried until the frame
    /// changes (one message per failed frame, not one per repaint).
    texture_failed_epoch: Option<u64>,
    show_avatar: bool,
    seed_geo: u64,
    seed_tex: u64,
    psi: f32,
    /// Whether the user (slider or automation) set ψ; until then each generation uses the
    /// loaded model's default and the slider shows it afterwards.
    psi_from_user: bool,
    /// Generation requested by a command before egui's context was available.
    queued: Option<(bool, GenerateArgs)>,
}

impl GetAvatarApp {
    pub fn new(cc: &eframe::CreationContext<'_>, startup: Vec<Action>, startup_errors: Vec<String>) -> Self {
        let mut status = Status::default();
        let mut messages = startup_errors;
        let mut engine = None;
        let viewer = match &cc.wgpu_render_state {
            Some(rs) => {
                match GenEngine::new(rs, cc.egui_ctx.clone()) {
                    Ok(e) => engine = Some(e),
                    Err(e) => messages.push(e),
                }
                let info = rs.adapter.get_info();
                // Browsers may hide the adapter's name; fall back to what they do report.
                status.adapter = [info.name.as_str(), info.driver.as_str(), info.driver_info.as_str()]
                    .into_iter()
                    .find(|s| !s.is_empty())
                    .map(str::to_string)
                    .unwrap_or_else(|| {
                        format!("{:?} adapter (vendor {:#x}, device {:#x})", info.device_type, info.vendor, info.device)
                    });
                status.backend = format!("{:?}", info.backend);
                Some(Viewer::new(&rs.device))
            }
            None => {
                messages.push("no wgpu render state: WebGPU is unavailable in this browser".into());
                None
            }
        };
        let body = match BodyModel::default_body() {
            Ok(b) => Some(b),
            Err(e) => {
                messages.push(format!("cannot load the embedded body model: {e}"));
                None
            }
        };
        let poses = PoseLibrary::builtin();
        let mut app = Self {
            body,
            params: poses.params("standing", &[]).unwrap_or_default(),
            poses,
            pose_name: "standing".into(),
            camera: OrbitCamera::default(),
            view: ViewMode::Rgb,
            res: 512,
            continuous: false,
            edit_joint: 16,
            viewer,
            mesh_dirty: true,
            avatar_dirty: true,
            render_dirty: true,
            status,
            frame_times: Default::default(),
            messages,
            engine,
            rigged: None,
            field: None,
            texture_image: None,
            texture_valid: false,
            texture_epoch: 0,
            texture_failed_epoch: None,
            texture_job: None,
            show_avatar: false,
            seed_geo: 0,
            seed_tex: 0,
            psi: default_psi(None),
            psi_from_user: false,
            queued: None,
        };
        for a in startup {
            app.apply(a);
        }
        app
    }

    fn apply(&mut self, action: Action) {
        match action {
            Action::Pose(name) => match self.poses.pose(&name) {
                Ok(p) => {
                    self.params.pose = p;
                    self.pose_name = name;
                    self.mesh_dirty = true;
                }
                Err(e) => self.messages.push(e.to_string()),
            },
            Action::Joint(j, v) => {
                self.params.pose[j] = Vec3::from_array(v);
                self.pose_name = "custom".into();
                self.mesh_dirty = true;
            }
            Action::Camera { yaw, pitch, radius } => {
                if let Some(y) = yaw {
                    self.camera.yaw = y;
                }
                if let Some(p) = pitch {
                    self.camera.pitch = p;
                }
                if let Some(r) = radius {
                    self.camera.radius = r;
                }
                self.camera = self.camera.clamped();
                self.render_dirty = true;
            }
            Action::View(v) => {
                self.view = v;
                self.render_dirty = true;
            }
            Action::Res(r) => {
                self.res = r;
                self.render_dirty = true;
            }
            Action::Betas(b) => {
                self.params.betas = b;
                self.mesh_dirty = true;
            }
            Action::ResetCamera => {
                self.camera = OrbitCamera::default();
                self.render_dirty = true;
            }
            Action::Download => self.download_glb(),
            Action::Continuous(c) => self.continuous = c,
            Action::Generate(a) => self.queued = Some((false, a)),
            Action::Retexture(a) => self.queued = Some((true, a)),
            Action::ShowAvatar(b) => {
                self.show_avatar = b && self.rigged.is_some();
                self.mesh_dirty = true;
                self.avatar_dirty = true;
            }
        }
    }

    /// Start a queued generation (needs egui's context for the repaint callback).
    fn start_queued(&mut self, ctx: &egui::Context) {
        let Some((texture_only, a)) = self.queued.take() else { return };
        let (Some(engine), Some(body)) = (self.engine.as_mut(), self.body.as_ref()) else {
            self.messages.push("the generator is not available (no WebGPU device for burn)".into());
            return;
        };
        if engine.busy {
            self.queued = Some((texture_only, a));
            return;
        }
        if let Some(g) = a.seed_geo {
            self.seed_geo = g;
        }
        if let Some(t) = a.seed_tex {
            self.seed_tex = t;
        }
        if let Some(p) = a.psi {
            self.psi = p;
            self.psi_from_user = true;
        }
        let keep = if texture_only { self.rigged.clone() } else { None };
        if texture_only && keep.is_none() {
            self.messages.push("generate an avatar before re-texturing it".into());
            return;
        }
        // Until the user sets ψ, the loaded model's default applies (0 for a checkpoint with
        // latent modes: its training subjects, `generator::default_psi`).
        let psi = self.psi_from_user.then_some(self.psi);
        engine.start(body, (self.seed_geo, self.seed_tex), psi, keep, ctx.clone());
    }

    fn poll_generation(&mut self) {
        let (Some(engine), Some(body)) = (self.engine.as_mut(), self.body.as_ref()) else { return };
        let polled = engine.poll(body);
        self.status.generating = engine.busy;
        self.status.model = engine.weights.describe();
        match polled {
            Some(Ok(done)) => {
                self.status.generations += 1;
                self.status.last_generation_ms = done.millis as f32;
                self.status.avatar_vertices = done.rigged.canonical.mesh.vertices.len();
                (self.seed_geo, self.seed_tex) = done.seeds;
                self.psi = done.psi;
                self.rigged = Some(done.rigged);
                self.field = Some(done.field);
                self.show_avatar = true;
                self.mesh_dirty = true;
                self.avatar_dirty = true;
                self.status.generating = false;
            }
            Some(Err(e)) => {
                self.messages.push(e);
                self.status.generating = false;
            }
            None => {}
        }
    }

    /// Current mesh to show/export: the re-posed avatar, or the posed body.
    fn current_mesh(&self) -> Option<(Vec<Vec3>, Vec<Vec3>, Vec<Vec3>, Vec<[u32; 3]>)> {
        let body = self.body.as_ref()?;
        let posed = pose_body(body, &self.params);
        if self.show_avatar {
            if let (Some(r), Some(ctx)) = (&self.rigged, self.engine.as_ref().and_then(|e| e.context())) {
                let (v, n) = r.repose(ctx, &posed);
                return Some((v, n, r.canonical.colors.clone(), r.canonical.mesh.faces.clone()));
            }
        }
        let normals = vertex_normals(&posed.vertices, &body.faces);
        let n = posed.vertices.len();
        Some((posed.vertices, normals, vec![SKIN; n], body.faces.clone()))
    }

    fn posed_mesh(&self) -> Option<ExportMesh> {
        let (positions, normals, colors, indices) = self.current_mesh()?;
        let what = if self.show_avatar { format!("avatar_{}_{}", self.seed_geo, self.seed_tex) } else { "body".into() };
        Some(ExportMesh {
            positions,
            normals,
            colors,
            uvs: Vec::new(),
            indices,
            name: format!("getavatar_{what}_{}", self.pose_name),
        })
    }

    fn download_glb(&mut self) {
        let Some(mesh) = self.posed_mesh() else {
            self.messages.push("no body to export".into());
            return;
        };
        match write_glb(&mesh) {
            Ok(bytes) => {
                let name = format!("getavatar_{}.glb", self.pose_name);
                match web::download_bytes(&name, &bytes, "model/gltf-binary") {
                    Ok(()) => {
                        self.status.downloads += 1;
                        self.status.last_glb_bytes = bytes.len();
                    }
                    Err(e) => self.messages.push(format!("download failed: {e}")),
                }
            }
            Err(e) => self.messages.push(format!("glTF export failed: {e}")),
        }
    }

    /// Upload what the current pose needs: for a rigged avatar only the bone transforms
    /// (its canonical mesh goes up once per avatar; the GPU re-poses it), for the bare body
    /// the posed vertices.
    fn upload_mesh(&mut self, rs: &eframe::egui_wgpu::RenderState) {
        let Some(body) = self.body.as_ref() else { return };
        let posed = pose_body(body, &self.params);
        let rig = match (&self.rigged, self.engine.as_ref().and_then(|e| e.context())) {
            (Some(r), Some(ctx)) if self.show_avatar => Some((r, ctx)),
            _ => None,
        };
        let Some(viewer) = self.viewer.as_mut() else { return };
        match rig {
            Some((r, ctx)) => {
                if self.avatar_dirty {
                    let c = &r.canonical;
                    let verts: Vec<Vertex> = (0..c.mesh.vertices.len())
                        .map(|i| Vertex {
                            position: c.mesh.vertices[i].to_array(),
                            normal: c.normals[i].to_array(),
                            color: c.colors[i].to_array(),
                            bone: r.body_vertex[i],
                        })
                        .collect();
                    viewer.set_mesh(&rs.device, &rs.queue, &verts, &c.mesh.faces, true);
                    self.status.vertices = verts.len();
                    self.status.triangles = c.mesh.faces.len();
                    self.avatar_dirty = false;
                }
                viewer.set_bones(&rs.device, &rs.queue, &bone_transforms(ctx, &posed));
            }
            None => {
                let normals = vertex_normals(&posed.vertices, &body.faces);
                let verts: Vec<Vertex> = posed
                    .vertices
                    .iter()
                    .zip(&normals)
                    .map(|(p, n)| Vertex {
                        position: p.to_array(),
                        normal: n.to_array(),
                        color: SKIN.to_array(),
                        bone: 0,
                    })
                    .collect();
                viewer.set_mesh(&rs.device, &rs.queue, &verts, &body.faces, false);
                self.status.vertices = verts.len();
                self.status.triangles = body.faces.len();
                // The next avatar shown must be uploaded again.
                self.avatar_dirty = true;
            }
        }
    }

    fn update_gpu(&mut self, frame: &eframe::Frame) {
        let Some(rs) = frame.wgpu_render_state() else {
            return;
        };
        if self.viewer.is_none() {
            return;
        }
        if !(self.mesh_dirty || self.render_dirty || self.continuous) {
            return;
        }
        let t0 = web::now_ms();
        // The per-pixel texture image no longer shows this frame.
        self.texture_valid = false;
        self.texture_epoch += 1;
        if self.mesh_dirty {
            self.upload_mesh(rs);
            self.mesh_dirty = false;
        }
        let Some(viewer) = self.viewer.as_mut() else { return };
        let view_proj = self.camera.projection_wgpu(1.0) * self.camera.world_to_camera();
        let mut renderer = rs.renderer.write();
        viewer.render(&rs.device, &rs.queue, &mut renderer, self.res, view_proj, self.camera.eye(), self.view);
        self.render_dirty = false;
        self.status.renders += 1;
        self.status.last_render_ms = (web::now_ms() - t0) as f32;
    }

    fn side_panel(&mut self, ui: &mut egui::Ui) {
        ui.heading("GETAvatar");
        ui.label(egui::RichText::new(format!("{} · {}", self.status.adapter, self.status.backend)).small());
        ui.separator();

        ui.strong("Generate");
        if let Some(e) = &self.engine {
            ui.label(egui::RichText::new(e.weights.describe()).small());
        }
        ui.horizontal(|ui| {
            ui.label("geometry seed");
            ui.add(egui::DragValue::new(&mut self.seed_geo));
            ui.label("texture seed");
            ui.add(egui::DragValue::new(&mut self.seed_tex));
        });
        if ui.add(egui::Slider::new(&mut self.psi, 0.0..=1.0).text("truncation ψ")).changed() {
            self.psi_from_user = true;
        }
        let busy = self.engine.as_ref().is_some_and(|e| e.busy);
        ui.horizontal(|ui| {
            if ui.add_enabled(!busy, egui::Button::new("Generate")).clicked() {
                self.apply(Action::Generate(GenerateArgs::default()));
            }
            if ui.add_enabled(!busy && self.rigged.is_some(), egui::Button::new("New texture only")).clicked() {
                self.seed_tex += 1;
                self.apply(Action::Retexture(GenerateArgs::default()));
            }
            if busy {
                ui.spinner();
            }
        });
        if self.rigged.is_some() {
            let mut show = self.show_avatar;
            if ui.checkbox(&mut show, "show avatar (off: bare body)").changed() {
                self.apply(Action::ShowAvatar(show));
            }
            ui.label(format!("{} vertices · {:.0} ms", self.status.avatar_vertices, self.status.last_generation_ms));
        }
        ui.separator();

        ui.strong("Pose");
        let mut chosen = None;
        ui.horizontal_wrapped(|ui| {
            for name in BUILTIN_POSE_NAMES {
                if ui
                    .selectable_label(self.pose_name == name, name)
                    .on_hover_text(self.poses.description(name).unwrap_or(""))
                    .clicked()
                {
                    chosen = Some(name.to_string());
                }
            }
        });
        if let Some(n) = chosen {
            self.apply(Action::Pose(n));
        }
        egui::CollapsingHeader::new("Joint rotations (axis-angle, rad)").default_open(false).show(ui, |ui| {
            egui::ComboBox::from_id_salt("joint").selected_text(JOINT_NAMES[self.edit_joint]).show_ui(ui, |ui| {
                for (j, n) in JOINT_NAMES.iter().enumerate() {
                    ui.selectable_value(&mut self.edit_joint, j, *n);
                }
            });
            let j = self.edit_joint.min(NUM_JOINTS - 1);
            let mut v = self.params.pose[j].to_array();
            let mut changed = false;
            for (axis, x) in ["x", "y", "z"].iter().zip(v.iter_mut()) {
                changed |=
                    ui.add(egui::Slider::new(x, -std::f32::consts::PI..=std::f32::consts::PI).text(*axis)).changed();
            }
            if changed {
                self.apply(Action::Joint(j, v));
            }
            if ui.button("Zero this joint").clicked() {
                self.apply(Action::Joint(j, [0.0; 3]));
            }
        });

        ui.separator();
        ui.strong("Shape β");
        if let Some(body) = &self.body {
            let names = body.shape_names.clone();
            let nb = body.num_betas;
            let mut betas = self.params.betas.clone();
            betas.resize(nb, 0.0);
            let mut changed = false;
            for (k, b) in betas.iter_mut().enumerate() {
                let label = names.get(k).cloned().unwrap_or_else(|| format!("β{k}"));
                changed |= ui.add(egui::Slider::new(b, -2.0..=2.0).text(label)).changed();
            }
            if ui.button("Reset shape").clicked() {
                betas = vec![0.0; nb];
                changed = true;
            }
            if changed {
                self.apply(Action::Betas(betas));
            }
        }

        ui.separator();
        ui.strong("View");
        ui.horizontal(|ui| {
            for m in [ViewMode::Rgb, ViewMode::Texture, ViewMode::Normal, ViewMode::Mask] {
                if ui.selectable_label(self.view == m, m.as_str()).clicked() {
                    self.apply(Action::View(m));
                }
            }
        });
        ui.horizontal(|ui| {
            ui.label("Resolution");
            for r in RESOLUTIONS {
                if ui.selectable_label(self.res == r, format!("{r}²")).clicked() {
                    self.apply(Action::Res(r));
                }
            }
        });
        ui.horizontal(|ui| {
            if ui.button("Reset camera").clicked() {
                self.apply(Action::ResetCamera);
            }
            ui.checkbox(&mut self.continuous, "continuous")
                .on_hover_text("re-render every frame (measures FPS under load)");
        });
        ui.label(format!(
            "{:.1} FPS · render {:.1} ms · {} verts · {} tris",
            self.status.fps, self.status.last_render_ms, self.status.vertices, self.status.triangles
        ));
        ui.label(egui::RichText::new("drag: orbit · wheel: zoom · double-click: reset").small());

        ui.separator();
        if ui.button("⬇ Download .glb").on_hover_text("posed mesh with normals, glTF 2.0 binary").clicked() {
            self.apply(Action::Download);
        }
        if !self.messages.is_empty() {
            ui.separator();
            for m in self.messages.iter().rev().take(5) {
                ui.colored_label(egui::Color32::from_rgb(230, 120, 100), m);
            }
        }
    }

    /// The paper's per-pixel RGB (Sec. 4.4) for the `texture` view: rasterise canonical
    /// coordinates on the GPU, read them back, query the texture field at every covered
    /// pixel (burn on the same device), and show the result. One job at a time; a job whose
    /// frame changed meanwhile is dropped and restarted.
    fn update_texture(&mut self, rs: &eframe::egui_wgpu::RenderState, ctx: &egui::Context) {
        let wanted = self.view == ViewMode::Texture && self.show_avatar && self.field.is_some();
        let (Some(viewer), Some(engine)) = (self.viewer.as_mut(), self.engine.as_mut()) else { return };
        match self.texture_job.take() {
            None => {
                let failed = self.texture_failed_epoch == Some(self.texture_epoch);
                if wanted && !self.texture_valid && !failed && viewer.request_canonical(&rs.device, &rs.queue, self.res)
                {
                    self.texture_job =
                        Some(TextureJob { epoch: self.texture_epoch, res: self.res, t0: web::now_ms(), pixels: None });
                }
            }
            Some(mut job) if job.pixels.is_none() => match viewer.take_canonical() {
                None => self.texture_job = Some(job),
                Some(Err(e)) => {
                    self.texture_failed_epoch = Some(job.epoch);
                    self.messages
                        .push(format!("per-pixel texture: {e}; retried when the camera, pose or avatar changes"));
                }
                Some(Ok(data)) => {
                    if job.epoch != self.texture_epoch || !wanted {
                        return;
                    }
                    let mut pixels = Vec::new();
                    let mut points = Vec::new();
                    for (i, p) in data.chunks_exact(4).enumerate() {
                        if p[3] > 0.5 {
                            pixels.push(i as u32);
                            points.push(Vec3::new(p[0], p[1], p[2]));
                        }
                    }
                    if let Some(field) = &self.field {
                        engine.query_texture(field.clone(), points, ctx.clone());
                        job.pixels = Some(pixels);
                        self.texture_job = Some(job);
                    }
                }
            },
            Some(job) => match engine.poll_texture() {
                None => self.texture_job = Some(job),
                Some(Err(e)) => {
                    self.texture_failed_epoch = Some(job.epoch);
                    self.messages
                        .push(format!("per-pixel texture: {e}; retried when the camera, pose or avatar changes"));
                }
                Some(Ok(colors)) => {
                    let Some(pixels) = job.pixels else { return };
                    if job.epoch != self.texture_epoch || !wanted {
                        return;
                    }
                    let n = job.res as usize;
                    let bg = crate::viewer::background(ViewMode::Texture);
                    let mut img =
                        egui::ColorImage::new([n, n], vec![egui::Color32::from_rgb(bg[0], bg[1], bg[2]); n * n]);
                    for (&i, c) in pixels.iter().zip(&colors) {
                        let e = (linear_to_srgb(*c) * 255.0).round().clamp(Vec3::ZERO, Vec3::splat(255.0));
                        img.pixels[i as usize] = egui::Color32::from_rgb(e.x as u8, e.y as u8, e.z as u8);
                    }
                    match &mut self.texture_image {
                        Some(h) => h.set(img, egui::TextureOptions::LINEAR),
                        None => {
                            self.texture_image =
                                Some(ctx.load_texture("per-pixel texture", img, egui::TextureOptions::LINEAR))
                        }
                    }
                    self.texture_valid = true;
                    self.status.texture_images += 1;
                    self.status.texture_pixels = pixels.len();
                    self.status.last_texture_ms = (web::now_ms() - job.t0) as f32;
                }
            },
        }
    }

    fn viewport(&mut self, ui: &mut egui::Ui) {
        let texture = match &self.texture_image {
            Some(h) if self.view == ViewMode::Texture && self.texture_valid && self.show_avatar => Some(h.id()),
            _ => None,
        };
        let Some(id) = texture.or_else(|| self.viewer.as_ref().and_then(|v| v.texture_id)) else {
            ui.centered_and_justified(|ui| ui.label("WebGPU is not available"));
            return;
        };
        let avail = ui.available_rect_before_wrap();
        let side = avail.width().min(avail.height()).max(64.0);
        let rect = egui::Rect::from_center_size(avail.center(), egui::vec2(side, side));
        let img = egui::Image::new(egui::load::SizedTexture::new(id, egui::vec2(side, side)))
            .sense(egui::Sense::click_and_drag());
        let resp = ui.put(rect, img);
        let r = resp.rect;
        self.status.viewport = [r.min.x, r.min.y, r.width(), r.height()];
        if resp.dragged() {
            let d = resp.drag_delta();
            self.camera.yaw -= d.x * 0.01;
            self.camera.pitch += d.y * 0.01;
            self.camera = self.camera.clamped();
            self.render_dirty = true;
        }
        if resp.double_clicked() {
            self.apply(Action::ResetCamera);
        }
        if resp.hovered() {
            let scroll = ui.input(|i| i.smooth_scroll_delta.y);
            if scroll != 0.0 {
                self.camera.radius *= (-scroll * 0.002).exp();
                self.camera = self.camera.clamped();
                self.render_dirty = true;
            }
        }
    }

    fn publish_status(&mut self, now: f64) {
        self.frame_times.push_back(now);
        while self.frame_times.front().is_some_and(|t| now - t > 1000.0) {
            self.frame_times.pop_front();
        }
        self.status.fps = self.frame_times.len() as f32;
        self.status.pose = self.pose_name.clone();
        self.status.view = self.view.as_str().into();
        self.status.res = self.res;
        self.status.yaw_deg = self.camera.yaw.to_degrees();
        self.status.pitch_deg = self.camera.pitch.to_degrees();
        self.status.radius = self.camera.radius;
        self.status.errors = self.messages.clone();
        self.status.ready = self.status.renders > 0;
        self.status.seed_geo = self.seed_geo;
        self.status.seed_tex = self.seed_tex;
        self.status.psi = self.psi;
        self.status.showing = if self.show_avatar { "avatar" } else { "body" }.into();
        web::publish_status(&self.status);
    }
}

impl eframe::App for GetAvatarApp {
    fn ui(&mut self, ui: &mut egui::Ui, frame: &mut eframe::Frame) {
        web::set_context(ui.ctx());
        self.poll_generation();
        for cmd in web::take_commands() {
            match cmd {
                Ok(a) => self.apply(a),
                Err(e) => self.messages.push(e),
            }
        }
        self.start_queued(&ui.ctx().clone());
        self.update_gpu(frame);
        if let Some(rs) = frame.wgpu_render_state() {
            let rs = rs.clone();
            self.update_texture(&rs, &ui.ctx().clone());
        }
        egui::Panel::left("controls").resizable(true).default_size(300.0).show(ui, |ui| {
            egui::ScrollArea::vertical().show(ui, |ui| self.side_panel(ui));
        });
        egui::CentralPanel::default().show(ui, |ui| self.viewport(ui));
        // Render changes made by this frame's widgets on the next frame.
        if self.mesh_dirty
            || self.render_dirty
            || self.continuous
            || self.queued.is_some()
            || self.texture_job.is_some()
            || (self.view == ViewMode::Texture
                && !self.texture_valid
                && self.field.is_some()
                && self.texture_failed_epoch != Some(self.texture_epoch))
        {
            ui.ctx().request_repaint();
        }
        self.publish_status(web::now_ms());
    }
}

/// The egui wgpu configuration: WebGPU, and a device with the adapter's own limits
/// (burn kernels need more storage buffers per stage than wgpu's defaults).
pub fn wgpu_options() -> egui_wgpu::WgpuConfiguration {
    use egui_wgpu::{wgpu, WgpuSetup, WgpuSetupCreateNew};
    let mut create = WgpuSetupCreateNew::without_display_handle();
    create.instance_descriptor.backends = wgpu::Backends::BROWSER_WEBGPU;
    create.device_descriptor = std::sync::Arc::new(|adapter: &wgpu::Adapter| wgpu::DeviceDescriptor {
        label: Some("getavatar device"),
        required_features: adapter.features() - wgpu::Features::MAPPABLE_PRIMARY_BUFFERS,
        required_limits: adapter.limits(),
        ..Default::default()
    });
    egui_wgpu::WgpuConfiguration { wgpu_setup: WgpuSetup::CreateNew(create), ..Default::default() }
}

/// A per-pixel texture image in the making (see `GetAvatarApp::update_texture`).
struct TextureJob {
    /// The frame it belongs to.
    epoch: u64,
    res: u32,
    t0: f64,
    /// Covered pixels (row-major indices) once the canonical coordinates are read back.
    pixels: Option<Vec<u32>>,
}
