//! The egui application: state and the per-frame flow (poll the generator → start queued
//! work → pose the body → upload → render → per-pixel texture → panels). The browser side
//! (`web.rs`) owns the app: it hands it automation commands and publishes its status.
//!
//! - `panels`: the side panel and the viewport
//! - `photo_panel`: "Reconstruct from photo" (detection, body fit, overlays, Download fit)
//! - `texture_job`: the per-pixel texture view's job
//! - `motion_panel`: motion playback (built-in clips, SMPL/AMASS files) and the downloads
//! - `reconstruct_panel`: "Reconstruct avatar" from the fitted photo (preset, progress,
//!   preview, Cancel)
//! - `video_panel`: "Motion from video…" (progress, ETA, Cancel; the clip joins the motions)

mod motion_panel;
mod panels;
mod photo_panel;
mod reconstruct_panel;
mod texture_job;
mod video_panel;

use std::rc::Rc;
use std::sync::Arc;

use eframe::egui;
use glam::Vec3;

use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::{pose_body, vertex_normals, BodyParams};
use getavatar_core::export::gltf_export::{write_glb, ExportMesh};
use getavatar_core::generator::pipeline::default_psi;
use getavatar_core::generator::rigging::RiggedAvatar;
use getavatar_core::OrbitCamera;

use crate::automation::{Action, GenerateArgs, Status, ViewMode};
use crate::generate::GenEngine;
use crate::platform::{download_bytes, now_ms};
use crate::texture_field::TextureField;
use crate::viewer::{joint_bones, Vertex, Viewer};
use motion_panel::MotionPlayer;
use photo_panel::PhotoPanel;
use reconstruct_panel::ReconstructPanel;
use texture_job::TextureJob;

/// The avatar shown (when it is, and the generator's body context is ready) with that context.
fn shown_rig<'a>(
    rigged: &'a Option<RiggedAvatar>,
    engine: &'a Option<GenEngine>,
    show: bool,
) -> Option<(&'a RiggedAvatar, &'a getavatar_core::generator::pipeline::BodyContext)> {
    match (rigged, engine.as_ref().and_then(|e| e.context())) {
        (Some(r), Some(ctx)) if show => Some((r, ctx)),
        _ => None,
    }
}

/// Linear RGB albedo of the untextured body.
const SKIN: Vec3 = Vec3::new(0.62, 0.42, 0.32);

/// Messages the app keeps (the status's `errors`).
const KEPT_MESSAGES: usize = 50;

pub struct GetAvatarApp {
    /// Shared (`Arc`): a fit takes it without copying its 25 MB of shape directions, a
    /// copy that held the UI thread ~50 ms.
    body: Option<Arc<BodyModel>>,
    poses: PoseLibrary,
    params: BodyParams,
    pose_name: String,
    camera: OrbitCamera,
    view: ViewMode,
    res: u32,
    continuous: bool,
    edit_joint: usize,
    viewer: Option<Viewer>,
    /// The pose changed: new joint transforms go up (and the mesh, if the shape changed).
    mesh_dirty: bool,
    /// What the uploaded mesh is (avatar or body, and the shape it is bound at), and that
    /// shape's rest joints.
    uploaded: Option<(bool, Vec<f32>)>,
    /// A new avatar's upload is timed into `status.last_generation_stages`.
    time_upload: bool,
    rest_joints: [Vec3; getavatar_core::NUM_JOINTS],
    /// The avatar's canonical mesh on the GPU is stale (new avatar, new texture, toggled).
    avatar_dirty: bool,
    /// Viewport must be re-rendered.
    render_dirty: bool,
    status: Status,
    frame_times: std::collections::VecDeque<f64>,
    messages: Vec<String>,
    /// Messages dropped from the front of `messages` (it keeps the last [`KEPT_MESSAGES`]).
    dropped_messages: u64,
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
    /// The photo → body flow.
    photo: PhotoPanel,
    /// The reconstruction from the fitted photo.
    recon: ReconstructPanel,
    /// The shown avatar's name in downloads (`avatar_<geo>_<tex>` or `reconstruction`).
    avatar_name: String,
    /// Motion playback.
    motion: MotionPlayer,
    /// Motion from a video.
    video: video_panel::VideoPanel,
    /// The downloads' texture side (0: vertex colours), the shown avatar's bake at it, and a
    /// download waiting for the bake.
    texture_res: usize,
    baked: Option<getavatar_core::generator::rigging::BakedTexture>,
    pending_download: Option<motion_panel::DownloadKind>,
    /// egui's context, for the repaints of background tasks.
    ctx: egui::Context,
}

impl GetAvatarApp {
    pub fn new(cc: &eframe::CreationContext<'_>, startup: Vec<Action>, startup_errors: Vec<String>) -> Self {
        let mut status = Status::default();
        let mut messages = startup_errors;
        let body = match BodyModel::default_body() {
            Ok(b) => Some(Arc::new(b)),
            Err(e) => {
                messages.push(format!("cannot load the embedded body model: {e}"));
                None
            }
        };
        let mut engine = None;
        let viewer = match &cc.wgpu_render_state {
            Some(rs) => {
                match GenEngine::new(rs, body.as_deref().cloned(), cc.egui_ctx.clone()) {
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
        let poses = PoseLibrary::builtin();
        // The built-in library always has "standing"; should it not, say so and start at rest.
        let params = poses.params("standing", &[]).unwrap_or_else(|e| {
            messages.push(format!("start pose: {e}"));
            BodyParams::default()
        });
        let mut app = Self {
            body,
            params,
            poses,
            pose_name: "standing".into(),
            camera: OrbitCamera::default(),
            view: ViewMode::Rgb,
            res: 512,
            continuous: false,
            edit_joint: 16,
            viewer,
            mesh_dirty: true,
            uploaded: None,
            time_upload: false,
            rest_joints: [Vec3::ZERO; getavatar_core::NUM_JOINTS],
            avatar_dirty: true,
            render_dirty: true,
            status,
            frame_times: Default::default(),
            messages,
            dropped_messages: 0,
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
            photo: PhotoPanel::default(),
            recon: ReconstructPanel::default(),
            avatar_name: "avatar".into(),
            motion: MotionPlayer::default(),
            video: Default::default(),
            texture_res: 1024,
            baked: None,
            pending_download: None,
            ctx: cc.egui_ctx.clone(),
        };
        for a in startup {
            app.apply(a);
        }
        app
    }

    /// Apply one action: a widget's, a URL parameter's or an automation command's.
    pub fn apply(&mut self, action: Action) {
        match action {
            Action::Pose(name) => match self.poses.pose(&name) {
                Ok(p) => {
                    self.leave_motion(true);
                    self.params.pose = p;
                    self.pose_name = name;
                    self.mesh_dirty = true;
                }
                Err(e) => self.messages.push(e.to_string()),
            },
            Action::Joint(j, v) => {
                self.leave_motion(false);
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
            Action::Download => self.request_download(motion_panel::DownloadKind::Posed),
            Action::Continuous(c) => self.continuous = c,
            Action::Generate(a) => self.queued = Some((false, a)),
            Action::Retexture(a) => self.queued = Some((true, a)),
            Action::ShowAvatar(b) => {
                self.show_avatar = b && self.rigged.is_some();
                self.mesh_dirty = true;
                self.avatar_dirty = true;
            }
            a @ (Action::Photo { .. } | Action::PhotoFit(_)) => self.apply_photo(a),
            a @ (Action::Reconstruct(_)
            | Action::ReconstructCancel
            | Action::SaveReconstruction
            | Action::OpenReconstruction(_)) => self.apply_reconstruct(a),
            Action::Motion(a) => self.apply_motion(a),
            Action::MotionFile { name, bytes } => self.load_motion_file(name, bytes),
            a @ (Action::Video { .. } | Action::VideoCancel) => self.apply_video(a),
            Action::DownloadAnimated => self.request_download(motion_panel::DownloadKind::Animated),
            Action::DownloadVrm => self.request_download(motion_panel::DownloadKind::Vrm),
            Action::DownloadVrma => self.download_vrma(),
            Action::TextureRes(r) => self.texture_res = r,
            Action::TextureDevice(d) => match self.engine.as_mut() {
                Some(e) => e.texture_device = d,
                None => self.messages.push("the generator is not available".into()),
            },
        }
    }

    /// Start a queued generation (needs egui's context for the repaint callback).
    fn start_queued(&mut self, ctx: &egui::Context) {
        let Some((texture_only, a)) = self.queued.take() else { return };
        let Some(engine) = self.engine.as_mut() else {
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
        let compute = a.device.unwrap_or(crate::automation::Compute::Auto);
        engine.start((self.seed_geo, self.seed_tex), psi, keep, compute, self.params.betas.clone(), ctx.clone());
    }

    fn poll_generation(&mut self) {
        let Some(engine) = self.engine.as_mut() else { return };
        let polled = engine.poll();
        self.status.generating = engine.busy;
        self.status.model = engine.weights.describe();
        self.status.worker_body_context = engine.worker_body_context();
        match polled {
            Some(Ok(done)) => {
                self.status.generations += 1;
                self.status.last_generation_ms = done.millis as f32;
                self.status.last_generation_stages = done.stages;
                self.status.last_generation_on = done.on;
                self.time_upload = true;
                self.status.avatar_vertices = done.rigged.canonical.mesh.vertices.len();
                (self.seed_geo, self.seed_tex) = done.seeds;
                self.avatar_name = format!("avatar_{}_{}", done.seeds.0, done.seeds.1);
                self.psi = done.psi;
                self.rigged = Some(done.rigged);
                self.field = Some(done.field);
                // The bake belongs to the previous avatar (or texture).
                self.baked = None;
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

    /// The bare body in the current pose, for the posed download.
    fn posed_body_mesh(&self) -> Option<ExportMesh> {
        let body = self.body.as_ref()?;
        let posed = pose_body(body, &self.params);
        let normals = vertex_normals(&posed.vertices, &body.faces);
        let n = posed.vertices.len();
        Some(ExportMesh {
            positions: posed.vertices,
            normals,
            colors: vec![SKIN; n],
            uvs: Vec::new(),
            indices: body.faces.clone(),
            name: format!("getavatar_body_{}", self.pose_name),
        })
    }

    fn download_glb(&mut self) {
        let rig = shown_rig(&self.rigged, &self.engine, self.show_avatar);
        let what = match rig {
            Some(_) => self.avatar_name.clone(),
            None => "body".to_string(),
        };
        let bytes = match rig {
            Some((r, ctx)) => {
                let name = format!("getavatar_{what}_{}", self.pose_name);
                r.posed_glb(ctx, &self.params, self.baked.as_ref(), &name)
            }
            None => match self.posed_body_mesh() {
                Some(mesh) => write_glb(&mesh),
                None => {
                    self.messages.push("no body to export".into());
                    return;
                }
            },
        };
        let textured = rig.is_some() && self.baked.is_some();
        match bytes {
            Ok(bytes) => {
                let name = format!("getavatar_{what}_posed_{}.glb", self.pose_name.replace(' ', "_"));
                match download_bytes(&name, &bytes, "model/gltf-binary") {
                    Ok(()) => {
                        self.status.downloads += 1;
                        self.status.last_glb_bytes = bytes.len();
                        self.status.motion.last_textured = textured;
                    }
                    Err(e) => self.messages.push(format!("download failed: {e}")),
                }
            }
            Err(e) => self.messages.push(format!("glTF export failed: {e}")),
        }
    }

    /// Upload what the current pose needs: the mesh in the rest pose at the current shape
    /// once per avatar/body and shape (with its top-4 joint weights; an avatar vertex takes
    /// its rigging body vertex's), then per pose only the 24 joint transforms, which the GPU
    /// blends (the downloaded glTF's skinning).
    fn upload_mesh(&mut self, rs: &eframe::egui_wgpu::RenderState) {
        let Some(body) = self.body.as_ref() else { return };
        let rig = shown_rig(&self.rigged, &self.engine, self.show_avatar);
        let Some(viewer) = self.viewer.as_mut() else { return };
        let key = (rig.is_some(), self.params.betas.clone());
        if self.avatar_dirty || self.uploaded.as_ref() != Some(&key) {
            let t0 = now_ms();
            let top4 = |w: &[f32; getavatar_core::NUM_JOINTS]| {
                let (j, w) = getavatar_core::export::skin_export::top4(w);
                (j.map(u32::from), w)
            };
            let (verts, faces): (Vec<Vertex>, &[[u32; 3]]) = match rig {
                Some((r, ctx)) => {
                    let (positions, normals) = r.bind_pose(ctx, &self.params.betas);
                    let c = &r.canonical;
                    let verts = (0..c.mesh.vertices.len())
                        .map(|i| {
                            let (joints, weights) = top4(&body.weights[r.body_vertex[i] as usize]);
                            Vertex {
                                position: positions[i].to_array(),
                                normal: normals[i].to_array(),
                                color: c.colors[i].to_array(),
                                canonical: c.mesh.vertices[i].to_array(),
                                joints,
                                weights,
                            }
                        })
                        .collect();
                    (verts, &c.mesh.faces)
                }
                None => {
                    let rest =
                        pose_body(body, &BodyParams { betas: self.params.betas.clone(), ..BodyParams::default() });
                    let normals = vertex_normals(&rest.vertices, &body.faces);
                    let verts = rest
                        .vertices
                        .iter()
                        .zip(&normals)
                        .zip(&body.weights)
                        .map(|((p, n), w)| {
                            let (joints, weights) = top4(w);
                            Vertex {
                                position: p.to_array(),
                                normal: n.to_array(),
                                color: SKIN.to_array(),
                                canonical: [0.0; 3],
                                joints,
                                weights,
                            }
                        })
                        .collect();
                    (verts, &body.faces)
                }
            };
            viewer.set_mesh(&rs.device, &rs.queue, &verts, faces, true, rig.is_some());
            self.status.vertices = verts.len();
            self.status.triangles = faces.len();
            self.rest_joints = body.regress_joints(&body.shaped_vertices(&self.params.betas));
            self.uploaded = Some(key);
            self.avatar_dirty = false;
            if std::mem::take(&mut self.time_upload) && rig.is_some() {
                if let Some(p) = self.status.last_generation_stages.as_mut() {
                    let host_ms = now_ms() - t0;
                    p.stages.push(getavatar_core::util::profile::StageTime {
                        stage: "upload".into(),
                        host_ms,
                        ..Default::default()
                    });
                }
            }
        }
        viewer.set_bones(&rs.device, &rs.queue, &joint_bones(&body.parents, &self.rest_joints, &self.params));
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
        let t0 = now_ms();
        // The per-pixel texture image no longer shows this frame.
        self.texture_valid = false;
        self.texture_epoch += 1;
        let uploaded_before = self.viewer.as_ref().map_or(0, |v| v.uploaded_bytes);
        if self.mesh_dirty {
            self.upload_mesh(rs);
            self.mesh_dirty = false;
        }
        let Some(viewer) = self.viewer.as_mut() else { return };
        let mut renderer = rs.renderer.write();
        viewer.render(&rs.device, &rs.queue, &mut renderer, self.res, &self.camera, self.view);
        viewer.time_frame(&rs.queue, t0);
        self.render_dirty = false;
        self.status.renders += 1;
        self.status.last_render_ms = (now_ms() - t0) as f32;
        self.status.last_frame_upload_bytes = viewer.uploaded_bytes - uploaded_before;
        self.status.mesh_uploads = viewer.mesh_uploads;
    }

    /// Report an error to the user (shown in the panel and in the status).
    pub fn report(&mut self, message: String) {
        self.messages.push(message);
    }

    /// The status after a frame drawn at `now` (ms): frame rate, camera, errors, counters.
    pub fn status(&mut self, now: f64) -> &Status {
        self.frame_times.push_back(now);
        while self.frame_times.front().is_some_and(|t| now - t > 1000.0) {
            self.frame_times.pop_front();
        }
        self.status.fps = self.frame_times.len() as f32;
        if let Some(v) = &self.viewer {
            self.status.last_frame_ms = v.last_frame_ms() as f32;
        }
        self.status.pose = self.pose_name.clone();
        self.status.view = self.view.as_str().into();
        self.status.res = self.res;
        self.status.yaw_deg = self.camera.yaw.to_degrees();
        self.status.pitch_deg = self.camera.pitch.to_degrees();
        self.status.radius = self.camera.radius;
        // An app left open for hours keeps the last messages only: the panel shows five,
        // the status the last KEPT_MESSAGES and how many there were in all.
        if self.messages.len() > KEPT_MESSAGES {
            let extra = self.messages.len() - KEPT_MESSAGES;
            self.messages.drain(..extra);
            self.dropped_messages += extra as u64;
        }
        self.status.errors = self.messages.clone();
        self.status.errors_total = self.dropped_messages + self.messages.len() as u64;
        self.status.ready = self.status.renders > 0;
        self.status.seed_geo = self.seed_geo;
        self.status.seed_tex = self.seed_tex;
        self.status.psi = self.psi;
        self.status.showing = if self.show_avatar { "avatar" } else { "body" }.into();
        self.motion_status();
        &self.status
    }

    /// One frame: everything but the automation hook, which the caller drives.
    pub fn frame(&mut self, ui: &mut egui::Ui, frame: &mut eframe::Frame) {
        let ctx = ui.ctx().clone();
        self.take_dropped(&ctx);
        self.poll_photo(&ctx);
        self.poll_video();
        self.poll_reconstruct(&ctx);
        self.poll_generation();
        self.start_queued(&ui.ctx().clone());
        self.advance_motion();
        self.poll_bake();
        self.update_gpu(frame);
        if let Some(rs) = frame.wgpu_render_state() {
            let rs = rs.clone();
            self.update_texture(&rs, &ui.ctx().clone());
        }
        egui::Panel::left("controls").resizable(true).default_size(300.0).show(ui, |ui| {
            egui::ScrollArea::vertical().show(ui, |ui| self.side_panel(ui));
        });
        self.status.photo_view = [0.0; 4];
        egui::CentralPanel::default().show(ui, |ui| {
            if self.photo.visible && self.photo.has_photo() {
                ui.columns(2, |cols| {
                    self.photo_view(&mut cols[0]);
                    self.viewport(&mut cols[1]);
                });
            } else {
                self.viewport(ui);
            }
        });
        // Render changes made by this frame's widgets on the next frame.
        if self.mesh_dirty
            || self.render_dirty
            || self.continuous
            || self.motion_playing()
            || self.pending_download.is_some()
            || self.queued.is_some()
            || self.texture_job.is_some()
            || (self.view == ViewMode::Texture
                && !self.texture_valid
                && self.field.is_some()
                && self.texture_failed_epoch != Some(self.texture_epoch))
        {
            ui.ctx().request_repaint();
        }
    }
}

/// A busy indicator that redraws three times a second. egui's spinner asks for a frame every
/// frame, which on a software GPU takes the GPU time the background job it stands for needs
/// (MediaPipe's WebGL in the detector's worker shares the GPU process with the page).
pub(crate) fn busy_indicator(ui: &mut egui::Ui) {
    let phase = (ui.input(|i| i.time) * 3.0) as usize % 3;
    ui.label(["●○○", "○●○", "○○●"][phase]);
    ui.ctx().request_repaint_after(std::time::Duration::from_millis(333));
}
