//! Motion playback: the built-in clips (walk, turn, wave), loaded SMPL/AMASS `.npz` files and
//! clips made from videos (`video_panel`)
//! play on the avatar and the bare body — each frame changes only the pose, so a rigged
//! avatar is re-posed on the GPU (new bone transforms, no generation) — with play / pause /
//! scrub / speed / loop, and the downloads: the posed .glb, the animated .glb (skinned,
//! with the chosen clips), the VRM 1.0 avatar (.vrm) and the chosen clips as VRM animations
//! (.vrma), named after what they hold.

use std::rc::Rc;

use eframe::egui;
use glam::Vec3;

use getavatar_core::body::humanoid::SkeletonNames;
use getavatar_core::body::motion::{Motion, BUILTIN_CLIPS, MOTION_FPS};
use getavatar_core::export::skin_export::{animated_body_glb, body_vrm, motion_vrma};
use getavatar_core::export::vrm_export::{AvatarOrigin, VrmMeta};

use super::GetAvatarApp;
use crate::automation::{Action, MotionArgs, MAX_MOTION_SPEED, TEXTURE_RESOLUTIONS};
use crate::platform::{download_bytes, now_ms, open_file_picker, MOTION_INPUT_ID};

/// What a download button asked for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum DownloadKind {
    Posed,
    Animated,
    Vrm,
}

/// Longest step one frame may advance a clip, seconds (a backgrounded tab does not jump).
const MAX_STEP_S: f32 = 0.1;

/// The motion section's state.
pub(super) struct MotionPlayer {
    clips: Vec<Motion>,
    /// Index into `clips` of the clip shown, if any.
    selected: Option<usize>,
    /// Per clip: whether the animated download holds it.
    include: Vec<bool>,
    playing: bool,
    /// Seconds from the clip's start.
    time: f32,
    speed: f32,
    looping: bool,
    /// Clock of the last advanced frame, ms.
    last_ms: Option<f64>,
    files_loaded: u64,
    notes: Vec<String>,
}

impl Default for MotionPlayer {
    fn default() -> Self {
        // The built-ins are fixed keyframes: they always build.
        let clips: Vec<Motion> = BUILTIN_CLIPS.iter().filter_map(|n| Motion::builtin(n).ok()).collect();
        let include = vec![false; clips.len()];
        Self {
            clips,
            selected: None,
            include,
            playing: false,
            time: 0.0,
            speed: 1.0,
            looping: true,
            last_ms: None,
            files_loaded: 0,
            notes: Vec::new(),
        }
    }
}

impl MotionPlayer {
    /// The time at which the selected clip ends (a looping clip's last frame leads back into
    /// its first one frame later).
    fn period(&self) -> f32 {
        match self.selected.map(|i| &self.clips[i]) {
            Some(m) if m.looping => m.len() as f32 / MOTION_FPS,
            Some(m) => m.duration(),
            None => 0.0,
        }
    }

    /// Stop playing (a pose chosen by hand takes over).
    pub(super) fn pause(&mut self) {
        self.playing = false;
    }

    /// Clips the animated download holds: the ticked ones, else the one selected.
    fn chosen(&self) -> Vec<&Motion> {
        let ticked: Vec<&Motion> =
            self.clips.iter().zip(&self.include).filter(|(_, inc)| **inc).map(|(m, _)| m).collect();
        if ticked.is_empty() {
            self.selected.map_or_else(Vec::new, |i| vec![&self.clips[i]])
        } else {
            ticked
        }
    }
}

impl GetAvatarApp {
    /// Apply a motion command (widgets and automation).
    pub(super) fn apply_motion(&mut self, a: MotionArgs) {
        if let Some(name) = a.clip {
            match self.motion.clips.iter().position(|m| m.name == name) {
                Some(i) => self.select_clip(i),
                None => {
                    let names: Vec<&str> = self.motion.clips.iter().map(|m| m.name.as_str()).collect();
                    self.messages.push(format!("unknown motion clip `{name}` (available: {})", names.join(", ")));
                    return;
                }
            }
        }
        if let Some(s) = a.speed {
            self.motion.speed = s.clamp(0.05, MAX_MOTION_SPEED);
        }
        if let Some(l) = a.looping {
            self.motion.looping = l;
        }
        if let Some(t) = a.time {
            self.motion.time = t.min(self.motion.period());
            self.show_motion_frame();
        }
        if let Some(p) = a.play {
            if p && self.motion.selected.is_none() {
                self.messages.push("choose a motion clip to play".into());
            } else {
                if p && self.motion.time >= self.motion.period() {
                    self.motion.time = 0.0;
                }
                self.motion.playing = p;
                self.motion.last_ms = None;
                self.show_motion_frame();
            }
        }
        if let Some(names) = a.include {
            let mut include = vec![false; self.motion.clips.len()];
            for n in names {
                match self.motion.clips.iter().position(|m| m.name == n) {
                    Some(i) => include[i] = true,
                    None => self.messages.push(format!("include: unknown motion clip `{n}`")),
                }
            }
            self.motion.include = include;
        }
    }

    fn select_clip(&mut self, i: usize) {
        self.motion.selected = Some(i);
        self.motion.time = 0.0;
        self.motion.last_ms = None;
        self.show_motion_frame();
    }

    /// A motion file (SMPL/AMASS .npz) from the picker, a drop or the JS hook: added to the
    /// clips and selected; a bad file gets one message and changes nothing.
    pub(super) fn load_motion_file(&mut self, name: String, bytes: Vec<u8>) {
        let stem = name.rsplit(['/', '\\']).next().unwrap_or(&name);
        let stem = stem.strip_suffix(".npz").unwrap_or(stem).to_string();
        match Motion::from_amass_npz(&bytes, &stem) {
            Ok(m) => {
                self.motion.files_loaded += 1;
                self.add_clip(m);
            }
            Err(e) => self.messages.push(format!("{name}: {e}")),
        }
    }

    /// A new clip (a motion file's, a video's) joins the clips, replacing one of its name,
    /// and is selected; its notes show under the controls.
    pub(super) fn add_clip(&mut self, m: Motion) {
        self.motion.notes = m.notes.iter().map(|n| format!("{}: {n}", m.name)).collect();
        let i = match self.motion.clips.iter().position(|c| c.name == m.name) {
            Some(i) => {
                self.motion.clips[i] = m;
                i
            }
            None => {
                self.motion.clips.push(m);
                self.motion.include.push(false);
                self.motion.clips.len() - 1
            }
        };
        self.select_clip(i);
    }

    /// Pose the body (and avatar) at the selected clip's current time.
    fn show_motion_frame(&mut self) {
        let Some(m) = self.motion.selected.map(|i| &self.motion.clips[i]) else { return };
        let p = m.sample(self.motion.time, &self.params.betas);
        self.params.pose = p.pose;
        self.params.transl = p.transl;
        self.pose_name = format!("motion {}", m.name);
        self.mesh_dirty = true;
    }

    /// Advance a playing clip by the time since the last frame × speed.
    pub(super) fn advance_motion(&mut self) {
        if !self.motion.playing || self.motion.selected.is_none() {
            return;
        }
        let now = now_ms();
        let dt = self.motion.last_ms.map_or(0.0, |t| ((now - t) / 1000.0) as f32).clamp(0.0, MAX_STEP_S);
        self.motion.last_ms = Some(now);
        let period = self.motion.period();
        let mut t = self.motion.time + dt * self.motion.speed;
        if t >= period {
            if self.motion.looping && period > 0.0 {
                t = t.rem_euclid(period);
            } else {
                t = period;
                self.motion.playing = false;
            }
        }
        self.motion.time = t;
        self.show_motion_frame();
    }

    /// The side panel's section.
    pub(super) fn motion_section(&mut self, ui: &mut egui::Ui) {
        ui.strong("Motion");
        let current = self.motion.selected.map_or("none".to_string(), |i| self.motion.clips[i].name.clone());
        let mut pick = None;
        ui.horizontal(|ui| {
            egui::ComboBox::from_id_salt("motion_clip").selected_text(current).show_ui(ui, |ui| {
                for (i, m) in self.motion.clips.iter().enumerate() {
                    if ui.selectable_label(self.motion.selected == Some(i), &m.name).clicked() {
                        pick = Some(m.name.clone());
                    }
                }
            });
            if ui
                .button("Load motion…")
                .on_hover_text("SMPL/AMASS .npz (poses, trans, mocap_framerate); or drop it on the page")
                .clicked()
            {
                if let Err(e) = open_file_picker(MOTION_INPUT_ID) {
                    self.messages.push(format!("cannot open the file chooser: {e}"));
                }
            }
        });
        if let Some(name) = pick {
            self.apply(Action::Motion(MotionArgs { clip: Some(name), play: Some(true), ..Default::default() }));
        }
        self.video_section(ui);
        if self.motion.selected.is_some() {
            ui.horizontal(|ui| {
                let label = if self.motion.playing { "⏸ Pause" } else { "▶ Play" };
                if ui.button(label).clicked() {
                    let play = !self.motion.playing;
                    self.apply(Action::Motion(MotionArgs { play: Some(play), ..Default::default() }));
                }
                let mut looping = self.motion.looping;
                if ui.checkbox(&mut looping, "loop").changed() {
                    self.apply(Action::Motion(MotionArgs { looping: Some(looping), ..Default::default() }));
                }
            });
            let period = self.motion.period();
            let mut t = self.motion.time;
            if ui.add(egui::Slider::new(&mut t, 0.0..=period.max(1e-3)).suffix(" s").text("time")).changed() {
                self.apply(Action::Motion(MotionArgs { time: Some(t), ..Default::default() }));
            }
            let mut speed = self.motion.speed;
            if ui
                .add(egui::Slider::new(&mut speed, 0.1..=MAX_MOTION_SPEED).logarithmic(true).suffix("×").text("speed"))
                .changed()
            {
                self.apply(Action::Motion(MotionArgs { speed: Some(speed), ..Default::default() }));
            }
        }
        for n in &self.motion.notes {
            ui.label(egui::RichText::new(n).small());
        }
        ui.separator();
        ui.horizontal(|ui| {
            ui.label("texture");
            for r in TEXTURE_RESOLUTIONS {
                let label = if r == 0 { "colours".to_string() } else { format!("{r}²") };
                if ui
                    .selectable_label(self.texture_res == r, label)
                    .on_hover_text(
                        "the avatar's baked base-colour texture in the downloads (colours: per-vertex, no texture)",
                    )
                    .clicked()
                {
                    self.apply(Action::TextureRes(r));
                }
            }
        });
        if self.pending_download.is_some() {
            ui.horizontal(|ui| {
                super::busy_indicator(ui);
                ui.label(format!("baking the {}² texture…", self.texture_res));
            });
        }
        ui.horizontal(|ui| {
            if ui.button("⬇ posed .glb").on_hover_text("the mesh in the pose shown, glTF 2.0 binary").clicked() {
                self.apply(Action::Download);
            }
            if ui
                .button("⬇ animated .glb")
                .on_hover_text("skinned to the 24 SMPL joints, with the chosen clips as animations")
                .clicked()
            {
                self.apply(Action::DownloadAnimated);
            }
        });
        ui.horizontal(|ui| {
            if ui
                .button("⬇ .vrm")
                .on_hover_text(
                    "VRM 1.0 for avatar apps and engines: T-pose, humanoid bones, licence (a photo's avatar: \
                     only the person photographed may use it)",
                )
                .clicked()
            {
                self.apply(Action::DownloadVrm);
            }
            if ui.button("⬇ .vrma").on_hover_text("the chosen clips as VRM animations, one file each").clicked() {
                self.apply(Action::DownloadVrma);
            }
        });
        ui.collapsing("clips in the animated .glb", |ui| {
            for (m, inc) in self.motion.clips.iter().zip(self.motion.include.iter_mut()) {
                ui.checkbox(inc, format!("{} ({:.1} s)", m.name, m.duration()));
            }
            ui.label(egui::RichText::new("none ticked: the clip selected").small());
        });
    }

    /// A download: the avatar's texture is baked first (at `texture_res`, once per avatar
    /// and size), then the file is written.
    pub(super) fn request_download(&mut self, kind: DownloadKind) {
        let avatar = self.show_avatar && self.rigged.is_some();
        let stale = self.baked.as_ref().map(|b| b.res) != Some(self.texture_res);
        if avatar && self.texture_res > 0 && stale {
            let (Some(engine), Some(field), Some(rigged)) =
                (self.engine.as_mut(), self.field.clone(), self.rigged.clone())
            else {
                self.messages.push("the generator is not available to bake the texture".into());
                return;
            };
            if self.pending_download.is_none() {
                engine.bake(field, rigged, self.texture_res, self.ctx.clone());
            }
            self.pending_download = Some(kind);
            return;
        }
        if !avatar || self.texture_res == 0 {
            self.baked = None;
        }
        match kind {
            DownloadKind::Posed => self.download_glb(),
            DownloadKind::Animated => self.download_animated(),
            DownloadKind::Vrm => self.download_vrm(),
        }
    }

    /// A finished bake: keep it and write the download that waited for it.
    pub(super) fn poll_bake(&mut self) {
        let Some(engine) = self.engine.as_mut() else { return };
        self.status.motion.baking = engine.baking;
        let Some((field, result)) = engine.poll_bake() else { return };
        self.status.motion.baking = false;
        // A bake that finished after the avatar or its colours changed (a generation, a
        // re-texture or a reconstruction landed meanwhile) belongs to the old one: drop it and
        // bake the avatar shown now for the download that waits.
        if !self.field.as_ref().is_some_and(|f| Rc::ptr_eq(f, &field)) {
            self.status.motion.stale_bakes += 1;
            if let Some(kind) = self.pending_download.take() {
                self.request_download(kind);
            }
            return;
        }
        match result {
            Ok(crate::generate::Baked { texture: b, millis, on, detail }) => {
                let s = &mut self.status.motion;
                s.bakes += 1;
                s.last_bake_ms = millis as f32;
                s.last_bake_on = on.to_string();
                s.last_bake_detail = detail;
                s.atlas_vertices = b.atlas.source.len();
                s.atlas_own_chart_faces = b.atlas.own_chart_faces;
                self.baked = Some(b);
                if let Some(kind) = self.pending_download.take() {
                    self.request_download(kind);
                }
            }
            Err(e) => {
                self.messages.push(e);
                self.pending_download = None;
            }
        }
    }

    /// "animated .glb": the avatar shown (or the bare body) skinned, bound in the rest pose,
    /// showing the current pose, with the chosen clips.
    pub(super) fn download_animated(&mut self) {
        let Some(body) = self.body.as_ref() else {
            self.messages.push("no body to export".into());
            return;
        };
        let clips: Vec<Motion> = self.motion.chosen().into_iter().cloned().collect();
        let clip_names = if clips.is_empty() {
            "rigged".to_string()
        } else {
            clips.iter().map(|m| m.name.as_str()).collect::<Vec<_>>().join("+")
        };
        let rig = super::shown_rig(&self.rigged, &self.engine, self.show_avatar);
        let textured = rig.is_some() && self.baked.is_some();
        let (what, bytes) = match rig {
            Some((r, ctx)) => {
                let what = self.avatar_name.clone();
                let name = format!("getavatar_{what}_{clip_names}");
                (what, r.animated_glb(ctx, &self.params, &clips, self.baked.as_ref(), &name, SkeletonNames::Smpl))
            }
            None => {
                let name = format!("getavatar_body_{clip_names}");
                ("body".to_string(), animated_body_glb(body, &self.params, &clips, &name, SkeletonNames::Smpl))
            }
        };
        match bytes {
            Ok(bytes) => {
                let file = format!("getavatar_{what}_animated_{clip_names}.glb");
                match download_bytes(&file, &bytes, "model/gltf-binary") {
                    Ok(()) => {
                        self.status.motion.animated_downloads += 1;
                        self.status.motion.last_animated_bytes = bytes.len();
                        self.status.motion.last_textured = textured;
                    }
                    Err(e) => self.messages.push(format!("download failed: {e}")),
                }
            }
            Err(e) => self.messages.push(format!("glTF export failed: {e}")),
        }
    }

    /// "⬇ .vrm": the avatar shown (or the bare body) as a VRM 1.0 avatar in its rest T-pose
    /// at the shape shown; a photo's avatar carries the most restrictive licence.
    pub(super) fn download_vrm(&mut self) {
        let Some(body) = self.body.as_ref() else {
            self.messages.push("no body to export".into());
            return;
        };
        let rig = super::shown_rig(&self.rigged, &self.engine, self.show_avatar);
        let what = if rig.is_some() { self.avatar_name.clone() } else { "body".to_string() };
        let origin = match &rig {
            None => AvatarOrigin::Body,
            Some(_) if self.avatar_name == "reconstruction" => AvatarOrigin::Photo,
            Some(_) => AvatarOrigin::Generated,
        };
        let meta = VrmMeta { name: format!("getavatar_{what}"), origin };
        let bytes = match rig {
            Some((r, ctx)) => r.vrm(ctx, &self.params.betas, self.baked.as_ref(), &meta, SkeletonNames::Smpl),
            None => body_vrm(body, &self.params.betas, &meta, SkeletonNames::Smpl),
        };
        match bytes {
            Ok(bytes) => match download_bytes(&format!("getavatar_{what}.vrm"), &bytes, "model/gltf-binary") {
                Ok(()) => {
                    self.status.motion.vrm_downloads += 1;
                    self.status.motion.last_vrm_bytes = bytes.len();
                    self.status.motion.last_textured = self.baked.is_some();
                }
                Err(e) => self.messages.push(format!("download failed: {e}")),
            },
            Err(e) => self.messages.push(format!("VRM export failed: {e}")),
        }
    }

    /// "⬇ .vrma": each chosen clip as a VRM animation on the skeleton of the body shape shown
    /// (the .vrm's), one file each.
    pub(super) fn download_vrma(&mut self) {
        let Some(body) = self.body.as_ref() else {
            self.messages.push("no body to export".into());
            return;
        };
        let clips: Vec<Motion> = self.motion.chosen().into_iter().cloned().collect();
        if clips.is_empty() {
            self.messages.push("choose a motion clip for the .vrma".into());
            return;
        }
        for m in &clips {
            let result = motion_vrma(body, &self.params.betas, m, SkeletonNames::Smpl)
                .map_err(|e| format!("VRM animation export failed: {e}"))
                .and_then(|bytes| {
                    download_bytes(&format!("getavatar_{}.vrma", m.name), &bytes, "model/gltf-binary")
                        .map_err(|e| format!("download failed: {e}"))
                });
            match result {
                Ok(()) => self.status.motion.vrma_downloads += 1,
                Err(e) => {
                    self.messages.push(e);
                    return;
                }
            }
        }
    }

    /// Fill `status.motion`.
    pub(super) fn motion_status(&mut self) {
        let m = &self.motion;
        let s = &mut self.status.motion;
        s.clips = m.clips.iter().map(|c| c.name.clone()).collect();
        s.clip = m.selected.map_or(String::new(), |i| m.clips[i].name.clone());
        s.playing = m.playing;
        s.time = m.time;
        s.duration = m.period();
        s.frames = m.selected.map_or(0, |i| m.clips[i].len());
        s.speed = m.speed;
        s.looping = m.looping;
        s.include = m.chosen().iter().map(|c| c.name.clone()).collect();
        s.files_loaded = m.files_loaded;
        s.notes = m.notes.clone();
        s.texture_res = self.texture_res;
    }

    pub(super) fn motion_playing(&self) -> bool {
        self.motion.playing
    }

    /// A pose chosen by hand: playback stops and the root goes back to the origin.
    pub(super) fn leave_motion(&mut self, reset_root: bool) {
        self.motion.pause();
        if reset_root {
            self.params.transl = Vec3::ZERO;
        }
    }
}
