//! The fuzz targets' bodies, one per parser of outside bytes: each takes arbitrary
//! bytes, parses them the way the app or the trainer does and uses what comes back; none may
//! panic, hang or allocate far beyond the input's size. The same file is compiled into the
//! cargo-fuzz crate (`fuzz/`, libFuzzer, nightly) and into `getavatar-tests`, whose
//! `fuzz_regressions` test replays every kept corpus and crash file through it on stable,
//! in CI. docs/reliability.md has the commands and the runs.

use getavatar_core::body::body_fit::fit::BodyFit;
use getavatar_core::body::body_fit::landmarks::PoseResult;
use getavatar_core::body::body_model::BodyModel;
use getavatar_core::body::motion::Motion;
use getavatar_core::body::pose_library::PoseLibrary;
use getavatar_core::body::skinning::pose_body;
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::io::dataset;
use getavatar_core::io::npz;
use getavatar_core::io::scan::{self, SmplParams};

/// A target's body: arbitrary bytes in, nothing out (a panic is the finding).
pub type Body = fn(&[u8]);

/// Every target: its name (the corpus directory `fuzz/corpus/NAME`, the binary
/// `fuzz/fuzz_targets/NAME.rs`) and its body.
pub const TARGETS: &[(&str, Body)] = &[
    ("npz", npz_archive),
    ("body_model", body_model),
    ("motion", motion),
    ("safetensors", safetensors),
    ("checkpoint", checkpoint_files),
    ("pose_library", pose_library),
    ("dataset_labels", dataset_labels),
    ("scan", scan_files),
    ("photo", photo),
    ("landmarks", landmarks),
    ("body_fit", body_fit),
    ("app_command", app_command),
];

/// Text inputs: files the programs read as UTF-8 (`read_to_string` refuses the rest).
fn text(data: &[u8]) -> Option<&str> {
    std::str::from_utf8(data).ok()
}

/// `.npz` archives (zip of `.npy`): every array read and converted.
pub fn npz_archive(data: &[u8]) {
    if let Ok(arrays) = npz::read_npz(data) {
        for (key, a) in &arrays {
            let _ = (a.to_f32(), a.to_f64(), a.to_i64(key), a.len(), a.dtype());
        }
    }
    let _ = npz::read_npz_arrays(data, Some(&["poses", "betas"]));
}

/// A body model `.npz` (SMPL layout), then posed and shaped with it.
pub fn body_model(data: &[u8]) {
    if let Ok(model) = BodyModel::from_npz_bytes(data) {
        let mut params = getavatar_core::BodyParams { betas: vec![0.5; model.num_betas], ..Default::default() };
        params.pose[1].z = 0.5;
        let _ = pose_body(&model, &params);
    }
}

/// An AMASS motion `.npz`, then sampled across its clip.
pub fn motion(data: &[u8]) {
    if let Ok(m) = Motion::from_amass_npz(data, "fuzz") {
        let d = m.duration();
        for t in [-1.0, 0.0, 0.37 * d, d, d + 1.0, f32::NAN] {
            let _ = m.sample(t, &[0.1; 10]);
        }
        let _ = m.params(m.len() - 1, &[]);
    }
}

/// The safetensors container and the generator config embedded in it.
pub fn safetensors(data: &[u8]) {
    if let Ok(st) = checkpoint::parse_safetensors(data) {
        let _ = checkpoint::checkpoint_config(&st);
    }
    let _ = checkpoint::parse_safetensors_lenient(data);
}

/// Checkpoint files as the app and the trainer load them: a generator (tiny config) with its
/// latent modes, an inverted avatar, a discriminator (its config from the file).
pub fn checkpoint_files(data: &[u8]) {
    #[allow(deprecated)]
    let device = Device::ndarray();
    let tiny = GeneratorConfig::tiny();
    let _ = checkpoint::load_generator_and_modes(data, &tiny, &device);
    let _ = checkpoint::load_inverted(data, &tiny, &device);
    let _ = checkpoint::load_discriminator(data, &device);
}

/// A pose library JSON, every pose turned into body parameters.
pub fn pose_library(data: &[u8]) {
    let Some(t) = text(data) else { return };
    if let Ok(lib) = PoseLibrary::from_json(t) {
        let names: Vec<String> = lib.names().map(str::to_owned).collect();
        for n in &names {
            let _ = (lib.description(n), lib.params(n, &[0.2; 10]));
        }
    }
}

/// A dataset's `dataset.json`, every label turned into a camera and a body.
pub fn dataset_labels(data: &[u8]) {
    let Some(t) = text(data) else { return };
    if let Ok(labels) = dataset::parse_labels(std::path::Path::new("dataset.json"), t) {
        for (_, l) in &labels {
            let _ = (l.body_params(), l.view(), l.to_floats());
        }
    }
}

/// A scan's files: OBJ (with its normals), MTL and the SMPL parameters JSON.
pub fn scan_files(data: &[u8]) {
    let Some(t) = text(data) else { return };
    if let Ok(mesh) = scan::parse_obj(t) {
        let _ = scan::corner_normals(&mesh);
        let _ = scan::write_obj(&mesh);
    }
    let _ = scan::parse_mtl(t);
    if let Ok(p) = SmplParams::from_json(t) {
        let _ = (p.body_params(), p.translation());
    }
}

/// A photo (PNG or JPEG) as `trainer fit-pose` / `invert` decode it, and a dataset image.
pub fn photo(data: &[u8]) {
    if let Ok(img) = dataset::decode_photo(data) {
        let _ = img.to_rgb8();
    }
    let _ = dataset::decode_png(data);
}

/// A MediaPipe Pose result (`fit-pose --keypoints`), with the observations the fit takes.
pub fn landmarks(data: &[u8]) {
    let Some(t) = text(data) else { return };
    if let Ok(r) = PoseResult::from_json(t) {
        let _ = r.joint_observations(640, 480);
    }
}

/// A fit.json (`invert --fit`, `export --fit`), with what the inversion computes from it.
pub fn body_fit(data: &[u8]) {
    let Some(t) = text(data) else { return };
    if let Ok(fit) = BodyFit::from_json(t) {
        let _ = (fit.body_params(), fit.photo_view_proj());
        let _ = fit.framing.to_ndc([1.0, 2.0]);
    }
}

/// The app's automation commands (JSON) and URL query parameters.
pub fn app_command(data: &[u8]) {
    let Some(t) = text(data) else { return };
    let _ = getavatar_web::automation::parse_command(t);
    let _ = getavatar_web::automation::parse_query(t);
}
