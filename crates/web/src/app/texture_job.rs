//! The per-pixel texture view's job (paper Sec. 4.4): canonical coordinates rasterised on
//! the GPU and read back, the texture field queried at every covered pixel, the image shown.

use eframe::egui;
use glam::Vec3;

use getavatar_core::render::colour::linear_to_srgb;

use super::GetAvatarApp;
use crate::automation::ViewMode;
use crate::platform::now_ms;

/// A per-pixel texture image in the making (see `GetAvatarApp::update_texture`).
pub(super) struct TextureJob {
    /// The frame it belongs to.
    epoch: u64,
    res: u32,
    t0: f64,
    /// Covered pixels (row-major indices) once the canonical coordinates are read back.
    pixels: Option<Vec<u32>>,
}

impl GetAvatarApp {
    /// The paper's per-pixel RGB (Sec. 4.4) for the `texture` view: rasterise canonical
    /// coordinates on the GPU, read them back, query the texture field at every covered
    /// pixel (burn on the same device), and show the result. One job at a time; a job whose
    /// frame changed meanwhile is dropped and restarted.
    pub(super) fn update_texture(&mut self, rs: &eframe::egui_wgpu::RenderState, ctx: &egui::Context) {
        let wanted = self.view == ViewMode::Texture && self.show_avatar && self.field.is_some();
        let (Some(viewer), Some(engine)) = (self.viewer.as_mut(), self.engine.as_mut()) else { return };
        match self.texture_job.take() {
            None => {
                let failed = self.texture_failed_epoch == Some(self.texture_epoch);
                if wanted && !self.texture_valid && !failed && viewer.request_canonical(&rs.device, &rs.queue, self.res)
                {
                    self.texture_job =
                        Some(TextureJob { epoch: self.texture_epoch, res: self.res, t0: now_ms(), pixels: None });
                }
            }
            Some(mut job) if job.pixels.is_none() => match viewer.take_canonical() {
                None => self.texture_job = Some(job),
                Some(Err(e)) => job_failed(&mut self.texture_failed_epoch, &mut self.messages, job.epoch, &e),
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
                Some(Err(e)) => job_failed(&mut self.texture_failed_epoch, &mut self.messages, job.epoch, &e),
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
                    self.status.last_texture_ms = (now_ms() - job.t0) as f32;
                }
            },
        }
    }
}

/// A job of frame `epoch` failed with `e`: say so once, and do not retry until the frame changes.
fn job_failed(failed_epoch: &mut Option<u64>, messages: &mut Vec<String>, epoch: u64, e: &dyn std::fmt::Display) {
    *failed_epoch = Some(epoch);
    messages.push(format!("per-pixel texture: {e}; retried when the camera, pose or avatar changes"));
}
