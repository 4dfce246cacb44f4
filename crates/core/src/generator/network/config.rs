//! Generator sizes. `paper` follows the reference code (see `../shared/reference/paper-code-facts.md`);
//! `demo` is sized for interactive use (well under a second on a laptop GPU, a few seconds on
//! 2 CPU cores); `tiny` is for tests.

use serde::{Deserialize, Serialize};

/// Largest tet grid a config may ask for: 192³ cubes are 42 M tets, beyond what a browser's
/// GPU memory and a checkpoint from elsewhere should be able to demand.
pub const MAX_TET_RES: usize = 192;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeneratorConfig {
    /// Name of the preset this config came from ("paper", "demo", "tiny" or "custom").
    pub name: String,
    /// Latent size of z_geo and z_tex.
    pub z_dim: usize,
    /// Intermediate latent size of w_geo and w_tex.
    pub w_dim: usize,
    /// Fully connected layers per mapping network.
    pub mapping_layers: usize,
    /// Learning-rate multiplier of the mapping networks (equalised lr).
    pub mapping_lr_mul: f32,
    /// w_avg tracking decay β (w_avg ← β·w_avg + (1−β)·mean(w)).
    pub w_avg_beta: f32,
    /// Triplane resolution (the backbone grows from 4² to this, a power of two).
    pub plane_res: usize,
    /// Channels per plane (geometry and texture planes alike).
    pub plane_channels: usize,
    /// Resolution of the texture planes where it is finer than `plane_res` (not in the paper):
    /// texture-only detail blocks carry the texture planes on from `plane_res`² by doublings
    /// ([`crate::generator::network::synthesis::TextureDetailBlock`]). A 64² plane over the canonical
    /// space's 2 m has 3.1 cm texels: stripes, hems and faces are finer than two of them.
    /// Absent (None): the texture planes are `plane_res`², as in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub texture_res: Option<usize>,
    /// Resolution of the geometry planes where it is finer than `plane_res` (not in the
    /// paper): geometry-only detail blocks ([`crate::generator::network::synthesis::GeometryDetailBlock`])
    /// carry the SDF-residual planes on by doublings, so the normal field (∇SDF) can hold
    /// surface detail finer than the 3.6 cm texels of the demo's 64² planes (the data's
    /// garment folds have 4–7 cm wavelengths). The tet grid, and so the mesh, stay as they
    /// are. Absent (None): the geometry planes are `plane_res`², as in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub geometry_res: Option<usize>,
    /// A texture plane over the canonical face alone (not in the paper;
    /// [`crate::generator::network::face_plane::FacePlane`]): a 128² texture plane has 1.8 cm texels, an
    /// eye is one of them, and the back of the head reads the same front-plane texels as the
    /// face. Absent (None): no face plane, as in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub face: Option<FacePlaneConfig>,
    /// Backbone channels at resolution r: min(channel_base / r, channel_max).
    pub channel_base: usize,
    pub channel_max: usize,
    /// Hidden width of the decoders.
    pub decoder_hidden: usize,
    /// Texture feature size before to-RGB.
    pub texture_features: usize,
    /// Tet grid cells per side (Kuhn grid, `(n+1)³` vertices), at most [`MAX_TET_RES`]. No
    /// weight depends on it (the DMTet offsets are bounded by its cell), so a file may be
    /// extracted on a finer grid than it was trained on.
    pub tet_res: usize,
    /// Template SDF samples per side.
    pub template_res: usize,
}

/// Where the face plane lies in canonical space and how fine it is (metres; the canonical
/// body's face looks along +z).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FacePlaneConfig {
    /// Texels per side.
    pub res: usize,
    /// Centre of the plane's window (x, y) and the z of the face's front (the nose tip).
    pub center: [f32; 3],
    /// Half the window's width and height.
    pub half_size: [f32; 2],
    /// How far behind the nose tip the plane still reaches (fully to `depth` − 2 cm, fading
    /// to nothing at `depth`): the cheeks and ears' front, not the back of the head.
    pub depth: f32,
}

/// Largest face plane a config may ask for.
pub const MAX_FACE_RES: usize = 256;

impl GeneratorConfig {
    /// The reference code's sizes.
    pub fn paper() -> Self {
        Self {
            name: "paper".into(),
            z_dim: 512,
            w_dim: 512,
            mapping_layers: 8,
            mapping_lr_mul: 0.01,
            w_avg_beta: 0.998,
            plane_res: 256,
            plane_channels: 32,
            texture_res: None,
            geometry_res: None,
            face: None,
            channel_base: 32768,
            channel_max: 512,
            decoder_hidden: 32,
            texture_features: 32,
            tet_res: 45,
            template_res: 128,
        }
    }

    /// Interactive size for the browser app and CPU sampling.
    pub fn demo() -> Self {
        Self {
            name: "demo".into(),
            z_dim: 128,
            w_dim: 128,
            mapping_layers: 4,
            plane_res: 64,
            plane_channels: 16,
            channel_base: 4096,
            channel_max: 128,
            decoder_hidden: 32,
            texture_features: 16,
            // 3.6 cm cells: the body template alone covers the posed body's silhouette with
            // IoU ≈ 0.92 (40 cells: ≈ 0.83, wrists and feet thinned; test
            // `demo_grid_resolves_the_posed_body`). The shipped demo file brings a finer
            // grid of its own (96, 2.4 cm: narrow gaps and outlines, see its model card),
            // which training from this preset pays for in step time.
            tet_res: 64,
            template_res: 160,
            ..Self::paper()
        }
    }

    /// Minimal size for tests.
    pub fn tiny() -> Self {
        Self {
            name: "tiny".into(),
            z_dim: 16,
            w_dim: 16,
            mapping_layers: 2,
            plane_res: 16,
            plane_channels: 8,
            channel_base: 256,
            channel_max: 16,
            decoder_hidden: 16,
            texture_features: 8,
            tet_res: 24,
            template_res: 64,
            ..Self::paper()
        }
    }

    /// Preset by name.
    pub fn preset(name: &str) -> Option<Self> {
        match name {
            "paper" => Some(Self::paper()),
            "demo" => Some(Self::demo()),
            "tiny" => Some(Self::tiny()),
            _ => None,
        }
    }

    /// Backbone channels at resolution `res`.
    pub fn channels(&self, res: usize) -> usize {
        (self.channel_base / res).clamp(1, self.channel_max)
    }

    /// Resolutions of the synthesis blocks: 4, 8, …, plane_res.
    pub fn block_resolutions(&self) -> Vec<usize> {
        let mut r = vec![4];
        while *r.last().unwrap_or(&4) < self.plane_res {
            let next = r.last().copied().unwrap_or(4) * 2;
            r.push(next);
        }
        r
    }

    /// Doublings of `plane_res` up to `limit`: 2·plane_res, …, limit (none for None).
    fn detail_resolutions(&self, limit: Option<usize>) -> Vec<usize> {
        let mut r = Vec::new();
        let mut res = self.plane_res * 2;
        while res <= limit.unwrap_or(0) {
            r.push(res);
            res *= 2;
        }
        r
    }

    /// Resolutions of the texture detail blocks: 2·plane_res, …, texture_res (none by default).
    pub fn texture_detail_resolutions(&self) -> Vec<usize> {
        self.detail_resolutions(self.texture_res)
    }

    /// Resolution of the texture planes.
    pub fn texture_plane_res(&self) -> usize {
        self.texture_detail_resolutions().last().copied().unwrap_or(self.plane_res)
    }

    /// Resolutions of the geometry detail blocks: 2·plane_res, …, geometry_res (none by default).
    pub fn geometry_detail_resolutions(&self) -> Vec<usize> {
        self.detail_resolutions(self.geometry_res)
    }

    /// Resolution of the geometry planes.
    pub fn geometry_plane_res(&self) -> usize {
        self.geometry_detail_resolutions().last().copied().unwrap_or(self.plane_res)
    }

    /// Check that the sizes are usable; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let pos = [
            ("z_dim", self.z_dim),
            ("w_dim", self.w_dim),
            ("mapping_layers", self.mapping_layers),
            ("plane_channels", self.plane_channels),
            ("decoder_hidden", self.decoder_hidden),
            ("texture_features", self.texture_features),
            ("tet_res", self.tet_res),
        ];
        for (name, v) in pos {
            if v == 0 {
                return Err(format!("config field `{name}` must be positive"));
            }
        }
        if self.tet_res > MAX_TET_RES {
            return Err(format!(
                "config field `tet_res` must be at most {MAX_TET_RES} (cubes per side; got {})",
                self.tet_res
            ));
        }
        if !self.plane_res.is_power_of_two() || self.plane_res < 4 {
            return Err(format!("config field `plane_res` must be a power of two ≥ 4 (got {})", self.plane_res));
        }
        for (field, res) in [("texture_res", self.texture_res), ("geometry_res", self.geometry_res)] {
            if let Some(t) = res {
                if !t.is_power_of_two() || t < self.plane_res || t > 16 * self.plane_res {
                    return Err(format!(
                        "config field `{field}` must be a power of two from plane_res ({}) to 16× it (got {t})",
                        self.plane_res
                    ));
                }
            }
        }
        if let Some(f) = &self.face {
            let finite = f.center.iter().chain(&f.half_size).chain([&f.depth]).all(|v| v.is_finite());
            if !(4..=MAX_FACE_RES).contains(&f.res)
                || !finite
                || f.half_size.iter().any(|&h| h <= 0.0)
                || f.depth <= 0.0
            {
                return Err(format!(
                    "config field `face` must have a res from 4 to {MAX_FACE_RES} and finite, positive sizes (got {f:?})"
                ));
            }
        }
        if self.template_res < 8 {
            return Err(format!("config field `template_res` must be ≥ 8 (got {})", self.template_res));
        }
        Ok(())
    }
}
