//! "Motion from video…" in the motion section: the file picker, a drop or the hook start
//! `crate::video`'s task; its progress (frames read / fitted of all, an ETA) and Cancel show
//! under the motion controls; the finished clip joins the clips like a loaded motion file,
//! plays, and goes into the animated .glb and the .vrma under the video's name.

use eframe::egui;

use getavatar_core::body::motion::Motion;

use super::GetAvatarApp;
use crate::automation::{Action, PhotoSource};
use crate::platform::{open_file_picker, VIDEO_INPUT_ID};
use crate::video::{self, Phase, VideoDone, VideoEvent, VideoInfo, VideoStep, VideoTask};
use crate::video_clip::{DEFAULT_READ_FPS, MAX_SECONDS, MAX_SIDE, READ_FPS};

/// The video's task and what it reported.
pub(super) struct VideoPanel {
    task: Option<VideoTask>,
    info: Option<VideoInfo>,
    step: Option<VideoStep>,
    /// Frames read per second of video by the next run (the picker's and drops').
    fps: u32,
}

impl Default for VideoPanel {
    fn default() -> Self {
        Self { task: None, info: None, step: None, fps: DEFAULT_READ_FPS }
    }
}

impl GetAvatarApp {
    /// `Action::Video` / `Action::VideoCancel`.
    pub(super) fn apply_video(&mut self, a: Action) {
        match a {
            Action::Video { source, fps } => self.start_video(source, fps.unwrap_or(self.video.fps)),
            Action::VideoCancel => match &self.video.task {
                Some(t) => t.cancel(),
                None => self.messages.push("no video is being read".into()),
            },
            _ => {}
        }
    }

    fn start_video(&mut self, source: PhotoSource, fps: u32) {
        if self.video.task.is_some() {
            self.messages.push("a video is being read already: cancel it first".into());
            return;
        }
        let Some(body) = self.body.clone() else {
            self.fail_video("no body model to fit".into());
            return;
        };
        let s = &mut self.status.video;
        s.state = "reading".into();
        s.read_fps = fps;
        (s.read, s.fitted, s.lost, s.eta_s, s.frames) = (0, 0, 0, 0.0, 0);
        s.name = match &source {
            PhotoSource::Url(u) => u.clone(),
            PhotoSource::Bytes { name, .. } => name.clone(),
        };
        s.message.clear();
        self.video.info = None;
        self.video.step = None;
        self.video.task = Some(video::make_motion(source, fps, body, crate::photo::fit_device(), self.ctx.clone()));
    }

    fn fail_video(&mut self, message: String) {
        let s = &mut self.status.video;
        s.state = "failed".into();
        s.failures += 1;
        s.eta_s = 0.0;
        s.message = message.clone();
        self.messages.push(message);
    }

    /// Drain the running task's events.
    pub(super) fn poll_video(&mut self) {
        let Some(task) = self.video.task.clone() else { return };
        for e in task.drain() {
            match e {
                VideoEvent::Opened(info) => {
                    let s = &mut self.status.video;
                    (s.width, s.height, s.seconds, s.frames) = (info.width, info.height, info.seconds, info.frames);
                    s.name = info.name.clone();
                    self.video.info = Some(info);
                }
                VideoEvent::Progress(p) => {
                    let s = &mut self.status.video;
                    s.state = if p.phase == Phase::Reading { "reading" } else { "fitting" }.into();
                    (s.read, s.fitted, s.lost, s.eta_s) = (p.read, p.fitted, p.lost, p.eta_s);
                    self.video.step = Some(p);
                }
                VideoEvent::Done(done) => self.video_done(*done),
                VideoEvent::Failed(m) => self.fail_video(m),
                VideoEvent::Cancelled => {
                    let s = &mut self.status.video;
                    s.state = "cancelled".into();
                    s.eta_s = 0.0;
                    s.message = "cancelled before any frame was fitted: no clip made".into();
                    self.messages.push(s.message.clone());
                }
            }
        }
        if task.finished() {
            self.video.task = None;
        }
    }

    fn video_done(&mut self, done: VideoDone) {
        let v = done.video;
        let read = self.status.video.frames;
        let mut notes = Vec::new();
        if done.cut {
            notes.push(format!("cancelled: the first {} of {read} frames read make the clip", v.frames));
        }
        notes.extend(v.motion.notes.iter().cloned());
        let message = format!(
            "{}: {} frames read at {} fps in {:.0} s, fitted in {:.0} s{}",
            v.motion.name,
            read,
            self.status.video.read_fps,
            done.read_ms / 1000.0,
            done.fit_ms / 1000.0,
            if v.lost.is_empty() { String::new() } else { format!("; {} without a readable person", v.lost.len()) }
        );
        let s = &mut self.status.video;
        s.state = "done".into();
        s.eta_s = 0.0;
        s.fitted = v.frames;
        s.lost = v.lost.len();
        s.read_ms = done.read_ms as f32;
        s.fit_ms = done.fit_ms as f32;
        s.clips_made += 1;
        s.message = message;
        let motion = Motion { notes, ..v.motion };
        self.add_clip(motion);
        self.apply(Action::Motion(crate::automation::MotionArgs { play: Some(true), ..Default::default() }));
    }

    /// The part of the motion section about videos: the button, the rate, progress, Cancel.
    pub(super) fn video_section(&mut self, ui: &mut egui::Ui) {
        ui.horizontal(|ui| {
            let running = self.video.task.is_some();
            let hover = format!(
                "MP4, WebM or MOV of one person, up to {MAX_SECONDS:.0} s and {MAX_SIDE} px; or drop it on the page. \
                 The video stays in this page."
            );
            if ui.add_enabled(!running, egui::Button::new("Motion from video…")).on_hover_text(hover).clicked() {
                if let Err(e) = open_file_picker(VIDEO_INPUT_ID) {
                    self.messages.push(format!("cannot open the file chooser: {e}"));
                }
            }
            ui.add_enabled_ui(!running, |ui| {
                egui::ComboBox::from_id_salt("video_fps")
                    .selected_text(format!("{} frames/s", self.video.fps))
                    .show_ui(ui, |ui| {
                        for f in READ_FPS {
                            ui.selectable_value(&mut self.video.fps, f, format!("{f} frames/s"));
                        }
                    })
                    .response
                    .on_hover_text("frames read per second of video: fewer are quicker, more follow quick moves");
            });
        });
        let Some(task) = self.video.task.clone() else {
            if !self.status.video.message.is_empty() {
                ui.label(egui::RichText::new(&self.status.video.message).small());
            }
            return;
        };
        ui.horizontal(|ui| {
            super::busy_indicator(ui);
            let what = match (self.video.step, &self.video.info) {
                (Some(p), _) => {
                    let phase = if p.phase == Phase::Reading { "reading frames" } else { "fitting" };
                    let eta = if p.eta_s > 0.0 { format!(", ~{:.0} s left", p.eta_s.ceil()) } else { String::new() };
                    format!("{phase} {}/{}{eta}", p.done, p.total)
                }
                (None, Some(i)) => format!("opened {} ({} frames)", i.name, i.frames),
                (None, None) => "opening the video…".into(),
            };
            ui.label(what);
            if ui.button("Cancel").on_hover_text("keep the frames fitted so far as a shorter clip").clicked() {
                task.cancel();
            }
        });
    }
}
