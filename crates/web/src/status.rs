//! What the app publishes every frame for tests and tools (`window.getavatar.status()`): plain
//! serde structs, one per panel. Pure Rust, compiled and tested natively like
//! [`crate::automation`], which re-exports them.

use serde::{Deserialize, Serialize};
/// What the app publishes every frame for tests and tools (`window.getavatar.status()`).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Status {
    /// The app has drawn at least one frame of the body.
    pub ready: bool,
    /// Graphics adapter name and backend (e.g. "BrowserWebGpu").
    pub adapter: String,
    pub backend: String,
    /// Number of 3D renders so far.
    pub renders: u64,
    /// Frames per second of the UI over the last second.
    pub fps: f32,
    /// Milliseconds of CPU time of the last pose + upload + render.
    pub last_render_ms: f32,
    /// Milliseconds from the start of the last frame whose GPU work has completed to that
    /// completion: host time, the GPU's queue and its work (0 before the first).
    pub last_frame_ms: f32,
    /// Bytes the last 3D render wrote to GPU buffers (mesh, joint transforms, uniforms).
    pub last_frame_upload_bytes: u64,
    /// Meshes uploaded to the viewport so far (new avatar, shape or body; not a new pose).
    pub mesh_uploads: u64,
    pub pose: String,
    pub view: String,
    pub res: u32,
    pub yaw_deg: f32,
    pub pitch_deg: f32,
    pub radius: f32,
    pub vertices: usize,
    pub triangles: usize,
    /// Viewport image rectangle in CSS pixels: [x, y, width, height].
    pub viewport: [f32; 4],
    /// Number of .glb downloads triggered.
    pub downloads: u64,
    /// Size in bytes of the last .glb.
    pub last_glb_bytes: usize,
    /// Which generator weights are in use ("trained demo model …", "loading …" or
    /// "untrained demo generator (random weights): why").
    pub model: String,
    /// Whether a generation is running.
    pub generating: bool,
    /// Completed generations (full or texture-only).
    pub generations: u64,
    /// Milliseconds of the last generation (network + extraction + readbacks).
    pub last_generation_ms: f32,
    /// The last generation by stage (mapping … rigging, then the mesh's upload): host ms,
    /// waits on the GPU, read-backs (`getavatar_core::util::profile`).
    pub last_generation_stages: Option<getavatar_core::util::profile::StageProfile>,
    /// Where the last generation ran: "the worker's CPU (burn NdArray)" on a software WebGPU
    /// adapter, else "the page's WebGPU device".
    pub last_generation_on: String,
    /// How the reconstruction worker's warm-up (on a software adapter) had the body's context:
    /// "read from the browser's cache in … ms (… MB)", "built in … ms, kept in the browser's
    /// cache (… MB in … ms)", "built in … ms; not kept: why", or why it did not get ready
    /// ahead; empty before it answers.
    pub worker_body_context: String,
    pub seed_geo: u64,
    pub seed_tex: u64,
    pub psi: f32,
    /// "body" or "avatar": what the viewport shows.
    pub showing: String,
    pub avatar_vertices: usize,
    /// Per-pixel texture images finished (view `texture`), and the pixels of the last one
    /// and its time (rasterise canonical coordinates, read back, query the texture field).
    pub texture_images: u64,
    pub texture_pixels: usize,
    pub last_texture_ms: f32,
    /// The photo → body flow.
    pub photo: PhotoStatus,
    /// The photo's rectangle in CSS pixels when it is shown: [x, y, width, height].
    pub photo_view: [f32; 4],
    /// Motion playback and the animated download.
    pub motion: MotionStatus,
    /// Motion from a video.
    pub video: VideoStatus,
    /// The reconstruction from the photo.
    pub reconstruct: ReconstructStatus,
    /// The "Open photo…" button's rectangle in CSS pixels (for the test that clicks it).
    pub open_photo_button: [f32; 4],
    /// Messages about rejected commands / parameters (the last 50, most recent last).
    pub errors: Vec<String>,
    /// How many messages there were in all.
    pub errors_total: u64,
}

/// The photo panel's state (`status().photo`).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct PhotoStatus {
    /// "none", "detecting", "fitting", "fitted", "failed" or "cancelled".
    pub state: String,
    /// Where the photo came from (file name or URL).
    pub name: String,
    /// The photo's size, pixels.
    pub width: usize,
    pub height: usize,
    /// The size the detector ran at: the photo downscaled to at most 4 MP.
    pub detected_width: usize,
    pub detected_height: usize,
    /// The last message about the photo (why it failed, which joints are missing, …).
    pub message: String,
    /// People in the photo (selfie segmentation's regions; null when it could not tell).
    pub people: Option<usize>,
    /// The fitted one of them by size (1 = the largest; null: read on the whole photo outside
    /// every region), and each one's box in the shown photo, normalised [x, y, w, h],
    /// largest first.
    pub person: Option<usize>,
    pub persons: Vec<[f32; 4]>,
    /// Degrees clockwise the photo was turned to read the person upright (0, 90, 180, 270);
    /// the shown photo, the keypoints and the fit are of the turned photo.
    pub rotation: u16,
    /// Pose runs the person finder made (candidates tried).
    pub tries: usize,
    /// The landmarks are Pose's reading of the mirrored photo, which put fewer limb
    /// landmarks off the person's mask than the first reading, or saw apart the hands that the
    /// first reading put in one place.
    pub mirrored: bool,
    /// Body joints the detector did not see (visibility < ½), SMPL names.
    pub missing_joints: Vec<String>,
    /// Limbs the last fit held where the user put them against the detector ("left arm", …;
    /// a re-fit from corrected joints, `BodyFit::held`).
    pub held: Vec<String>,
    /// Milliseconds of the detection (decode, MediaPipe, mask read-back).
    pub detect_ms: f32,
    /// Fit progress: stage ("torso", "body", "silhouette"), steps done and total, loss.
    pub stage: String,
    pub steps_done: usize,
    pub steps_total: usize,
    pub loss: f32,
    /// Milliseconds of the last fit and its steps per second.
    pub fit_ms: f32,
    /// Completed fits (re-fits included) and failed photos.
    pub fits: u64,
    pub failures: u64,
    /// The last fit's residuals: mean keypoint distance in photo pixels and over the
    /// person's height, and the IoU of the fitted body with the person mask.
    pub mean_px: f32,
    pub relative_to_height: f32,
    pub mask_iou: Option<f32>,
    /// Downloads of fit.json + kp.json.
    pub fit_downloads: u64,
}

/// The reconstruction's state (`status().reconstruct`).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct ReconstructStatus {
    /// "none", "starting", "refitting" (the body on the guess's outline, on the page),
    /// "latent" (W+), "pivotal" (PTI), "finishing", "measuring" (the figures of a result on
    /// screen), "done", "failed" or "cancelled".
    pub state: String,
    pub message: String,
    /// The quality preset that runs (instant, fast, full): the panel's buttons show it.
    pub preset: String,
    /// The preset's or the request's steps: done in both phases, and in all.
    pub steps_done: usize,
    pub steps_total: usize,
    /// The render size the photo is compared at.
    pub res: usize,
    /// The start (latent mode or w_avg) and of how many candidates.
    pub start: String,
    pub candidates: usize,
    /// Why the start, the garment codes or the body's refit are not what was asked for ("":
    /// they are), e.g. an encoder file that cannot be used: the search started instead.
    pub start_note: String,
    /// The garment code whose geometry replaced the encoder's guess's
    /// (`reconstruction::garment_codes`; "" when the guess's own geometry stayed).
    pub garment: String,
    /// How many garment codes the encoder file carries, and how many were weighed (none when
    /// the guess's outline already overlaps the person well).
    pub garment_codes: usize,
    pub garments_weighed: usize,
    /// The codes were weighed against the guess's avatar as the job that showed it made it
    /// (the worker keeps it), not generated again.
    pub garment_guess_reused: bool,
    /// Whether the perceptual term (the shipped discriminator's features) is on.
    pub perceptual: bool,
    /// Where the steps run: "worker" (the reconstruction worker, off the UI thread) or "page"
    /// (where the worker cannot start).
    pub runs_in: String,
    /// The device they run on, in words ("CPU (burn NdArray in the worker; …)", "WebGPU: …").
    pub device: String,
    /// Milliseconds from "Reconstruct" to the first avatar on screen (the start's, shown
    /// before any refinement), and its mask IoU and masked PSNR (dB) at the photo's camera
    /// (NaN, null in JSON: the encoder's guess shown unmeasured, before the body's refit on
    /// its outline and the stage that measures).
    pub first_avatar_ms: f32,
    pub first_mask_iou: f32,
    pub first_psnr_db: f32,
    /// Cancelled after this many steps, the avatar being that state (0: not).
    pub stopped_at: usize,
    /// The photo's body fit refined on the first guess's outline: β₁ before and after (both 0:
    /// not refined).
    pub refit_beta1: [f32; 2],
    /// Where that refit ran ("page": on the guess already rigged there, "worker": inside the
    /// stage's job, "": none), its milliseconds on the page, and the milliseconds from
    /// "Reconstruct" to the guess on the refitted body on screen (0: not yet).
    pub refit_on: String,
    pub refit_ms: f32,
    pub refitted_avatar_ms: f32,
    /// Every step's weighted loss, in order (this run's).
    pub losses: Vec<f32>,
    /// The last step's mask IoU with the person mask.
    pub step_mask_iou: f32,
    /// Steps whose render's outline collapsed, after which the phase went on from its best
    /// state at half the rate (`inversion::COLLAPSED_IOU`).
    pub restarts: usize,
    /// Milliseconds per step so far (all, W+ steps, PTI steps), and the estimated seconds left.
    pub ms_per_step: f32,
    pub ms_per_latent_step: f32,
    pub ms_per_pivotal_step: f32,
    pub eta_s: f32,
    /// Milliseconds to load the model and choose the start, and of the finish (the final
    /// figures from the last step's render, the result file, extraction, rigging, the photo's
    /// projection).
    pub start_ms: f32,
    pub finish_ms: f32,
    /// Where the finish's time went, e.g. "worker: final figures 0.4 s, rigging 3.0 s, result
    /// file 0.2 s; page: the avatar 1.5 s (building the generator 40 ms)".
    pub finish_detail: String,
    /// Previews shown, and the steps done at the latest.
    pub previews: u64,
    pub preview_step: usize,
    /// The finished result at the photo's camera (the last step's render, before its update):
    /// mask IoU with the person mask and masked PSNR (dB); and its total milliseconds.
    pub mask_iou: f32,
    pub psnr_db: f32,
    pub total_ms: f32,
    /// Completed reconstructions.
    pub done: u64,
    /// Reconstructions opened from files, and saved ("Save reconstruction"; the last file's
    /// size in bytes).
    pub opened: u64,
    pub saved: u64,
    pub saved_bytes: usize,
    /// Whether the shown reconstruction keeps its photo (projected onto its texture).
    pub has_photo: bool,
}

/// What a reconstruction stage does, for its opening line ([`ReconstructStatus::stage_message`]).
pub struct StageStart<'a> {
    /// The stage the user started (else the one after the encoder's guess).
    pub first: bool,
    /// It refits the body on the start's outline, weighs the garment codes, runs steps.
    pub refits: bool,
    pub garments: bool,
    pub refines: bool,
    /// A first stage's start in words ("the photo encoder's guess", …).
    pub opening: &'a str,
    /// Appended (e.g. " (perceptual term off: …)").
    pub note: &'a str,
}

impl ReconstructStatus {
    /// A stage's opening line: a first stage's start, or after the guess how long it took (and
    /// the page's refit) and what this stage does.
    pub fn stage_message(&self, st: &StageStart) -> String {
        let refitted = match self.refit_on.as_str() {
            "page" => format!(", refitted to its outline in {:.1} s", self.refit_ms / 1000.0),
            _ => String::new(),
        };
        let first = self.first_avatar_ms / 1000.0;
        let after_guess = |what: &str| format!("the encoder's guess in {first:.1} s{refitted}; {what}…{}", st.note);
        match st {
            StageStart { first: true, .. } => format!("{}…{}", st.opening, st.note),
            StageStart { refits: true, garments: true, refines: false, .. } => {
                after_guess("weighing the garment codes, then fitting the body to the chosen outline")
            }
            StageStart { refits: true, refines: false, .. } => after_guess("fitting the body to its outline"),
            StageStart { refits: true, .. } => after_guess("fitting the body to its outline, then refining it"),
            StageStart { refines: false, .. } => after_guess("projecting the photo on it at the refitted camera"),
            _ => after_guess("refining it"),
        }
    }

    /// A finished job's last line, with why its start is not the one asked for where it is not.
    pub fn with_start_note(&self, message: String) -> String {
        match self.start_note.as_str() {
            "" => message,
            note => format!("{message} — {note}"),
        }
    }

    /// The first avatar in words: the encoder's guess, or the start the search chose (where no
    /// encoder file could be used, [`ReconstructStatus::start_note`] says why).
    pub fn first_avatar_name(&self) -> String {
        match self.candidates {
            0 | 1 => self.start.clone(),
            n => format!("the start from {} (the best of {n})", self.start),
        }
    }
}

/// Motion playback, for the tests.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct MotionStatus {
    /// Clips available (built-ins, then loaded files), by name.
    pub clips: Vec<String>,
    /// The selected clip ("" for none), whether it plays, where, and its length.
    pub clip: String,
    pub playing: bool,
    pub time: f32,
    pub duration: f32,
    pub frames: usize,
    pub speed: f32,
    pub looping: bool,
    /// Clips the animated download holds.
    pub include: Vec<String>,
    /// Motion files loaded, and what loading the last one changed (resampled, cut, …).
    pub files_loaded: u64,
    pub notes: Vec<String>,
    /// Animated downloads and the last one's size, bytes.
    pub animated_downloads: u64,
    pub last_animated_bytes: usize,
    /// VRM avatar downloads, VRM animation files downloaded, and the last file's size, bytes.
    pub vrm_downloads: u64,
    pub vrma_downloads: u64,
    pub last_vrm_bytes: usize,
    /// The downloads' texture side (0: vertex colours), finished bakes, whether one runs,
    /// the last one's milliseconds and its atlas (vertices, and triangles in own charts).
    pub texture_res: usize,
    pub bakes: u64,
    pub baking: bool,
    pub last_bake_ms: f32,
    /// Where the last bake's texture-field queries ran ("the worker's CPU (burn NdArray)" on a
    /// software adapter, "the page's WebGPU device"; empty before the first bake).
    pub last_bake_on: String,
    /// The last bake's stages: the atlas and texels, the texture-field queries, the image (ms).
    pub last_bake_detail: String,
    pub atlas_vertices: usize,
    pub atlas_own_chart_faces: usize,
    /// Bakes dropped because the avatar or its colours changed while they ran.
    pub stale_bakes: u64,
    /// Whether the last download (posed or animated) carried a texture.
    pub last_textured: bool,
}

/// Motion from a video (`status().video`).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct VideoStatus {
    /// "idle", "reading" (decoding frames and finding the person), "fitting", "done",
    /// "failed" or "cancelled".
    pub state: String,
    /// The video's name, size in pixels and length in seconds (0 before one is open).
    pub name: String,
    pub width: usize,
    pub height: usize,
    pub seconds: f32,
    /// Frames read per second of video, and how many frames that makes.
    pub read_fps: u32,
    pub frames: usize,
    /// Frames read (detected), frames fitted, and frames without a readable person.
    pub read: usize,
    pub fitted: usize,
    pub lost: usize,
    /// Seconds left, estimated from the pace so far (0 when not running).
    pub eta_s: f32,
    /// Milliseconds spent reading and fitting the last clip.
    pub read_ms: f32,
    pub fit_ms: f32,
    /// Clips made from videos, failures, and the last outcome in one sentence.
    pub clips_made: u64,
    pub failures: u64,
    pub message: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stage_says_where_it_starts_and_what_it_does() {
        let s = ReconstructStatus {
            first_avatar_ms: 2140.0,
            refit_on: "page".into(),
            refit_ms: 900.0,
            ..Default::default()
        };
        let st = |first, refits, garments, refines| StageStart {
            first,
            refits,
            garments,
            refines,
            opening: "choosing the start among the model's subjects (x.safetensors cannot be used (bad))",
            note: " (perceptual term off: none)",
        };
        assert_eq!(
            s.stage_message(&st(true, true, true, true)),
            "choosing the start among the model's subjects (x.safetensors cannot be used (bad))… (perceptual term off: none)"
        );
        assert_eq!(
            s.stage_message(&st(false, true, true, false)),
            "the encoder's guess in 2.1 s, refitted to its outline in 0.9 s; weighing the garment codes, then \
             fitting the body to the chosen outline… (perceptual term off: none)"
        );
        let worker = ReconstructStatus { refit_on: "worker".into(), ..s };
        assert_eq!(
            worker.stage_message(&st(false, true, false, true)),
            "the encoder's guess in 2.1 s; fitting the body to its outline, then refining it… (perceptual term off: none)"
        );
        assert!(worker.stage_message(&st(false, false, false, false)).contains("; projecting the photo on it"));
        assert!(worker.stage_message(&st(false, false, false, true)).contains("; refining it…"));
    }

    #[test]
    fn the_first_avatar_is_named_by_its_start() {
        let guess = ReconstructStatus { start: "the encoder's guess".into(), candidates: 1, ..Default::default() };
        assert_eq!(guess.first_avatar_name(), "the encoder's guess");
        let searched = ReconstructStatus { start: "mode 8".into(), candidates: 65, ..Default::default() };
        assert_eq!(searched.first_avatar_name(), "the start from mode 8 (the best of 65)");
        assert_eq!(searched.with_start_note("done".into()), "done");
        let noted =
            ReconstructStatus { start_note: "e.safetensors cannot be used (bad): searched …".into(), ..searched };
        assert_eq!(noted.with_start_note("done".into()), "done — e.safetensors cannot be used (bad): searched …");
    }
}
