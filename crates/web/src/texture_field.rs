//! An avatar's texture field (the paper's per-point colour network, Sec. 4.3): the generator
//! and codes it belongs to (the engine's model, or a reconstruction's tuned one), its
//! triplanes, and for a reconstruction the photo's projection. Its colours at canonical
//! points (the per-pixel view, a new texture, a bake's texels) come from the reconstruction
//! worker's CPU on a software WebGPU adapter ([`TextureField::colours`]), else from the
//! page's WebGPU device.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::{inverted_codes, save_inverted_async, SafeTensors};
use getavatar_core::generator::network::synthesis::Triplanes;
use getavatar_core::generator::network::GeneratorConfig;
use getavatar_core::generator::pipeline::{Generator, Styles};
use getavatar_core::generator::rigging::bake_queries;
use getavatar_core::reconstruction::photo_projection::{PhotoProjection, SourcePhoto};

use crate::reconstruct::{colours_in_worker, WorkerField};

/// Where colours were computed, for the status.
pub const ON_WORKER: &str = "the worker's CPU (burn NdArray)";
pub const ON_PAGE: &str = "the page's WebGPU device";

/// An avatar's texture field: its generator (the engine's, or a reconstruction's tuned one),
/// styles, and triplanes once computed (a new generation computes them inside the
/// extraction; they are made again only if the per-pixel texture view asks); and for a
/// reconstruction the photo's projection, which the bake blends in.
pub struct TextureField {
    model: RefCell<FieldModel>,
    planes: RefCell<Option<Triplanes>>,
    /// A reconstruction's: the photo it was made from and its projection onto the avatar.
    pub(crate) projection: Option<Rc<Projected>>,
    /// A reconstruction's field (its own tuned generator), which "Save reconstruction" keeps.
    reconstructed: bool,
    /// How the worker names this field (a generated identity's seeds and ψ, or a
    /// reconstruction's file, sent along) to compute its colours; None: only the page can.
    worker: Option<(WorkerField, Option<Rc<Vec<u8>>>)>,
}

thread_local! {
    /// Keys of reconstruction files handed to the worker (its cache tells them apart).
    static RESULT_KEYS: Cell<u64> = const { Cell::new(0) };
}

/// Where a texture field's generator and codes are.
pub enum FieldModel {
    /// On the page's device.
    Built(Rc<Generator>, Box<Styles>),
    /// In the reconstruction worker's result file, parsed: built on the page's device on first
    /// use (every weight onto the device in one task, 15–115 ms on SwiftShader), so a
    /// reconstruction shows its avatar without that task; the file itself is what "Save
    /// reconstruction" writes.
    File { st: Rc<SafeTensors>, bytes: Rc<Vec<u8>>, cfg: GeneratorConfig, device: Device },
}

/// A photo projected onto a reconstructed avatar.
pub struct Projected {
    pub photo: SourcePhoto,
    pub projection: PhotoProjection,
}

impl TextureField {
    /// A reconstruction's field: its tuned generator and codes, the photo's projection, and
    /// its file where the page has one (for the worker's texture-field queries).
    pub fn reconstructed(model: FieldModel, projection: Option<Rc<Projected>>, file: Option<Rc<Vec<u8>>>) -> Self {
        let worker = file.map(|bytes| {
            let key = RESULT_KEYS.with(|k| {
                k.set(k.get() + 1);
                k.get()
            });
            (WorkerField::Result { key }, Some(bytes))
        });
        Self { model: RefCell::new(model), planes: RefCell::new(None), projection, reconstructed: true, worker }
    }

    /// A generated identity's field: the model's generator and the styles of `seeds` and ψ
    /// (which the worker computes again from the same model), and its triplanes when the
    /// generation computed them.
    pub fn generated(g: Rc<Generator>, styles: Styles, planes: Option<Triplanes>, seeds: (u64, u64), psi: f32) -> Self {
        Self {
            model: RefCell::new(FieldModel::Built(g, Box::new(styles))),
            planes: RefCell::new(planes),
            projection: None,
            reconstructed: false,
            worker: Some((WorkerField::Seeds { seeds, psi }, None)),
        }
    }

    /// Whether this is a reconstruction's field.
    pub fn is_reconstruction(&self) -> bool {
        self.reconstructed
    }

    /// The generator and codes, built from the file on first use.
    fn model(&self) -> Result<(Rc<Generator>, Styles), String> {
        let built = match &*self.model.borrow() {
            FieldModel::Built(g, s) => return Ok((g.clone(), (**s).clone())),
            FieldModel::File { st, cfg, device, .. } => {
                inverted_codes(st, cfg, device).map_err(|e| format!("the reconstruction's file: {e}"))?
            }
        };
        let (g, s) = (Rc::new(built.0), built.1);
        *self.model.borrow_mut() = FieldModel::Built(g.clone(), Box::new(s.clone()));
        Ok((g, s))
    }

    /// The reconstruction as one file (`trainer invert`'s `inverted.safetensors` format: the
    /// tuned generator, the codes and the photo), for "Save reconstruction".
    pub async fn save_async(&self, cfg: &GeneratorConfig) -> Result<Vec<u8>, String> {
        if let FieldModel::File { bytes, .. } = &*self.model.borrow() {
            return Ok(bytes.to_vec());
        }
        let (g, styles) = self.model()?;
        let mut extra = std::collections::BTreeMap::new();
        extra.insert("inversion/source".into(), "the GETAvatar web app".into());
        let photo = self.projection.as_ref().map(|p| &p.photo);
        save_inverted_async(&g, cfg, &styles, photo, &extra).await.map_err(|e| e.to_string())
    }

    /// The generator, codes and triplanes (computed on first use).
    fn planes(&self) -> Result<(Rc<Generator>, Styles, Triplanes), String> {
        let (g, styles) = self.model()?;
        let cached = self.planes.borrow().clone();
        let planes = cached.unwrap_or_else(|| {
            let p = g.triplanes(&styles);
            *self.planes.borrow_mut() = Some(p.clone());
            p
        });
        Ok((g, styles, planes))
    }

    /// The field's linear RGB at canonical `points` and where it was computed: in the
    /// reconstruction worker on its CPU when `worker` (the model's config and checkpoint) is
    /// given and the worker can (a software adapter: its NdArray beats SwiftShader), else, or
    /// when the worker fails (the console says why), on the page's `device`.
    pub async fn colours(
        &self,
        points: &[glam::Vec3],
        device: &Device,
        worker: Option<(&GeneratorConfig, &Rc<Vec<u8>>)>,
    ) -> Result<(Vec<glam::Vec3>, &'static str), String> {
        let in_worker = match (worker, &self.worker) {
            (Some((cfg, checkpoint)), Some((field, result))) => {
                colours_in_worker(cfg, checkpoint, field, result.as_ref(), points).await
            }
            _ => Err(String::new()),
        };
        match in_worker {
            Ok((c, _)) => Ok((c, ON_WORKER)),
            Err(why) => {
                fell_back("the texture field's colours", &why);
                let (g, styles, planes) = self.planes()?;
                let c = bake_queries(&g, &planes, &styles, points, device).await.map_err(|e| e.to_string())?;
                Ok((c, ON_PAGE))
            }
        }
    }
}

/// Say in the console why the worker did not do `what` (nothing when it was not asked).
pub fn fell_back(what: &str, why: &str) {
    if !why.is_empty() {
        web_sys::console::warn_1(&format!("{what} in the worker failed ({why}); on the page instead").into());
    }
}
