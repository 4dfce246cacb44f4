//! The side panel (generate, photo, pose, shape, view, motion and downloads, messages) and the viewport
//! (the rendered image with orbit/zoom input). Widgets turn into [`Action`]s applied by
//! [`GetAvatarApp::apply`], the same path JS automation commands take.

use eframe::egui;

use getavatar_core::body::body_model::{JOINT_NAMES, NUM_JOINTS};
use getavatar_core::body::pose_library::BUILTIN_POSE_NAMES;

use super::GetAvatarApp;
use crate::automation::{Action, GenerateArgs, ViewMode, RESOLUTIONS};

impl GetAvatarApp {
    pub(super) fn side_panel(&mut self, ui: &mut egui::Ui) {
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
                super::busy_indicator(ui);
            }
        });
        if self.rigged.is_some() {
            let mut show = self.show_avatar;
            if ui.checkbox(&mut show, "show avatar (off: bare body)").changed() {
                self.apply(Action::ShowAvatar(show));
            }
            let (st, ms) = (&self.status, self.status.last_generation_ms);
            ui.label(format!("{} vertices · {ms:.0} ms on {}", st.avatar_vertices, st.last_generation_on));
            if let Some(p) = &self.status.last_generation_stages {
                ui.label(format!(
                    "host {:.0} ms · GPU waits {:.0} ms · {} read-back{}",
                    p.host_ms(),
                    p.gpu_wait_ms(),
                    p.readbacks(),
                    if p.readbacks() == 1 { "" } else { "s" }
                ))
                .on_hover_text(p.table());
            }
        }
        ui.separator();
        self.photo_section(ui);
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
        self.motion_section(ui);
        if !self.messages.is_empty() {
            ui.separator();
            for m in self.messages.iter().rev().take(5) {
                ui.colored_label(egui::Color32::from_rgb(230, 120, 100), m);
            }
        }
    }

    pub(super) fn viewport(&mut self, ui: &mut egui::Ui) {
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
}
