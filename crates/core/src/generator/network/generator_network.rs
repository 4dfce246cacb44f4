//! The generator's networks as one burn module (paper Sec. 4.1): the mapping networks, the
//! triplane synthesis, the decoders (SDF residual, DMTet offset, RGB) and the face plane, and
//! the styles (W+ per branch) the mapping makes of latents. What they are evaluated on (the
//! posed grid, the surface) is `crate::generator::pipeline`'s pipeline; this module knows no geometry
//! beyond the reference box.

use burn::module::Module;
use burn::tensor::{Device, Tensor};

use super::decoders::Decoders;
use super::face_plane::FacePlane;
use super::init::Rng;
use super::mapping::{
    nearest_mode, truncate_toward_modes, truncate_toward_subject, LatentModes, MappingNetwork, ModePairing,
};
use super::synthesis::{TriplaneSynthesis, Triplanes};
use super::triplane::sample_triplanes;
use super::GeneratorConfig;

#[derive(Module, Debug)]
pub struct Generator {
    pub mapping_geo: MappingNetwork,
    pub mapping_tex: MappingNetwork,
    pub synthesis: TriplaneSynthesis,
    pub decoders: Decoders,
    /// The face plane (`GeneratorConfig::face`; not in the paper), added to the texture
    /// features on the canonical face.
    pub face: Option<FacePlane>,
}

/// Whether the parameter at checkpoint path `name` (e.g. `decoders.texture.out.weight`)
/// belongs to the texture branch: the w_tex mapping network, the backbone's to-texture
/// layers, the texture detail blocks, the face plane, the texture decoder and its RGB head. Only the RGB image depends on them; the
/// shared backbone and everything geometric are outside it. Training may give this branch its
/// own learning rate (`optim::Adam::step_scaled`).
pub fn is_texture_param(name: &str) -> bool {
    name.starts_with("mapping_tex.")
        || name.contains(".to_texture.")
        || name.starts_with("synthesis.texture_detail.")
        || is_face_param(name)
        || name.starts_with("decoders.texture.")
        || name.starts_with("decoders.to_rgb.")
}

/// Whether the parameter at checkpoint path `name` belongs to the face plane.
pub fn is_face_param(name: &str) -> bool {
    name.starts_with("face.")
}

/// Whether the parameter at checkpoint path `name` belongs to the heads that place the
/// surface: the SDF-residual and DMTet-offset decoders.
pub fn is_geometry_head_param(name: &str) -> bool {
    name.starts_with("decoders.sdf.") || name.starts_with("decoders.offset.")
}

/// Per-layer styles (W+): `[B, n, w_dim]` each.
#[derive(Clone, Debug)]
pub struct Styles {
    pub geo: Tensor<3>,
    pub tex: Tensor<3>,
}

impl Generator {
    /// A generator with deterministic random weights from `seed`.
    pub fn new(cfg: &GeneratorConfig, seed: u64, device: &Device) -> Self {
        let mut rng = Rng::new(seed, 1);
        let mapping = |rng: &mut Rng| {
            MappingNetwork::new(rng, cfg.z_dim, cfg.w_dim, cfg.mapping_layers, cfg.mapping_lr_mul, device)
        };
        Self {
            mapping_geo: mapping(&mut rng),
            mapping_tex: mapping(&mut rng),
            synthesis: TriplaneSynthesis::new(&mut rng, cfg, device),
            decoders: Decoders::new(&mut rng, cfg, device),
            // Drawn last: configs without a face plane initialise as before.
            face: cfg.face.as_ref().map(|f| FacePlane::new(&mut rng, cfg, f, device)),
        }
    }

    /// Number of per-layer styles: (geometry: backbone + 2 decoder layers, texture: to-texture
    /// layers + 2 decoder layers + to-RGB).
    pub fn num_ws(&self) -> (usize, usize) {
        (self.synthesis.num_ws_geo() + 2, self.synthesis.num_ws_tex() + 3)
    }

    /// Map latents to W+ styles with truncation ψ towards w_avg. `z_geo`, `z_tex`: `[B, z_dim]`.
    pub fn styles(&self, z_geo: Tensor<2>, z_tex: Tensor<2>, psi: f32) -> Styles {
        self.styles_with(z_geo, z_tex, psi, None)
    }

    /// Like [`Generator::styles`]; with `modes`, ψ truncates towards the training subjects'
    /// codes instead of w_avg (multi-modal truncation): both branches towards the subject whose
    /// geometry mode is nearest to w_geo ([`truncate_toward_subject`]), or each branch towards
    /// its own nearest mode ([`truncate_toward_modes`]), as `modes.pairing` says.
    /// With per-layer texture modes (`modes.tex_layers`), the texture styles also get
    /// (1 − ψ) of the chosen texture mode's layer offsets.
    pub fn styles_with(&self, z_geo: Tensor<2>, z_tex: Tensor<2>, psi: f32, modes: Option<&LatentModes>) -> Styles {
        let (wg, wt) = (self.mapping_geo.forward(z_geo), self.mapping_tex.forward(z_tex));
        // The texture mode each row goes to, where the modes have layer offsets to add.
        let tex_mode = modes.and_then(|m| {
            let layers = m.tex_layers.as_ref().filter(|_| psi != 1.0)?;
            let k = match m.pairing {
                ModePairing::Branch => nearest_mode(&wt, &m.tex),
                ModePairing::Subject => nearest_mode(&wg, &m.geo),
            };
            Some(layers.clone().select(0, k))
        });
        let (wg, wt) = match modes {
            Some(m) if m.pairing == ModePairing::Branch => {
                (truncate_toward_modes(wg, &m.geo, psi), truncate_toward_modes(wt, &m.tex, psi))
            }
            Some(m) => truncate_toward_subject(wg, wt, &m.geo, &m.tex, psi),
            None => (self.mapping_geo.truncate(wg, psi), self.mapping_tex.truncate(wt, psi)),
        };
        let s = self.styles_from_w(wg, wt);
        match tex_mode {
            Some(layers) => Styles { tex: s.tex + layers * (1.0 - psi), geo: s.geo },
            None => s,
        }
    }

    /// `modes` of this generator's checkpoint before it grew texture detail blocks
    /// (`checkpoint::load_generator_growing`): the new blocks' style layers, which come after
    /// the file's detail blocks and before the 3 decoder layers, get zero offsets, so every
    /// subject renders as before. Modes without layer offsets, or with this generator's
    /// count, are returned as they are; more layers than this generator has is an error.
    pub fn grown_modes(&self, modes: LatentModes) -> Result<LatentModes, String> {
        let Some(layers) = &modes.tex_layers else { return Ok(modes) };
        let [k, have, w] = layers.dims();
        let (_, nt) = self.num_ws();
        if have == nt {
            return Ok(modes);
        }
        if have > nt || have < 3 {
            return Err(format!("texture mode offsets of {have} layers; this generator has {nt}"));
        }
        let zeros = Tensor::zeros([k, nt - have, w], &layers.device());
        let at = have - 3;
        let grown = Tensor::cat(vec![layers.clone().narrow(1, 0, at), zeros, layers.clone().narrow(1, at, 3)], 1);
        Ok(LatentModes { tex_layers: Some(grown), ..modes })
    }

    /// The styles of training subject `geo`'s geometry mode and subject `tex`'s texture mode
    /// (with its layer offsets, where the modes have them): a subject as trained, or re-textured
    /// with another's colours. None out of range.
    pub fn subject_styles(&self, modes: &LatentModes, geo: usize, tex: usize) -> Option<Styles> {
        let (wg, wt) = modes.subject(geo, tex)?;
        let s = self.styles_from_w(wg, wt);
        Some(match &modes.tex_layers {
            Some(l) => Styles { tex: s.tex + l.clone().narrow(0, tex, 1), geo: s.geo },
            None => s,
        })
    }

    /// Styles from W codes `[B, w_dim]` per branch (each repeated over its layers), e.g. a
    /// training subject's modes (`LatentModes::subject`).
    pub fn styles_from_w(&self, w_geo: Tensor<2>, w_tex: Tensor<2>) -> Styles {
        let (ng, nt) = self.num_ws();
        Styles {
            geo: w_geo.unsqueeze_dim::<3>(1).repeat_dim(1, ng),
            tex: w_tex.unsqueeze_dim::<3>(1).repeat_dim(1, nt),
        }
    }

    pub fn triplanes(&self, s: &Styles) -> Triplanes {
        let (ng, nt) = self.num_ws();
        self.synthesis.forward(s.geo.clone().narrow(1, 0, ng - 2), s.tex.clone().narrow(1, 0, nt - 3))
    }

    /// [`Generator::triplanes`] with a checkpoint after each synthesis block (the browser).
    pub async fn triplanes_async(&self, s: &Styles) -> Triplanes {
        let (ng, nt) = self.num_ws();
        self.synthesis.forward_async(s.geo.clone().narrow(1, 0, ng - 2), s.tex.clone().narrow(1, 0, nt - 3)).await
    }

    /// The geometry planes of `s` alone ([`TriplaneSynthesis::forward_geometry_async`]): the
    /// texture outputs and detail blocks are skipped.
    pub async fn geometry_planes_async(&self, s: &Styles) -> Tensor<4> {
        let (ng, _) = self.num_ws();
        self.synthesis.forward_geometry_async(s.geo.clone().narrow(1, 0, ng - 2)).await
    }

    fn w(ws: &Tensor<3>, i: usize) -> Tensor<2> {
        let [b, _, d] = ws.dims();
        ws.clone().narrow(1, i, 1).reshape([b, d])
    }

    /// SDF residual and DMTet offsets at canonical points `[B, N, 3]` → (`[B, N]`, `[B, N, 3]`).
    pub fn geometry_fields(&self, planes: &Triplanes, s: &Styles, points: Tensor<3>) -> (Tensor<2>, Tensor<3>) {
        self.geometry_fields_of(&planes.geometry, s, points)
    }

    /// [`Generator::geometry_fields`] from the geometry planes alone.
    pub fn geometry_fields_of(&self, geometry: &Tensor<4>, s: &Styles, points: Tensor<3>) -> (Tensor<2>, Tensor<3>) {
        let (ng, _) = self.num_ws();
        let feat = sample_triplanes(geometry.clone(), points);
        let residual = self.decoders.sdf_residual(feat.clone(), Self::w(&s.geo, ng - 2));
        let [b, n, _] = residual.dims();
        let offset = self.decoders.vertex_offset(feat, Self::w(&s.geo, ng - 1));
        (residual.reshape([b, n]), offset)
    }

    /// SDF residual only, `[B, N]`.
    pub fn sdf_residual(&self, planes: &Triplanes, s: &Styles, points: Tensor<3>) -> Tensor<2> {
        let (ng, _) = self.num_ws();
        let feat = sample_triplanes(planes.geometry.clone(), points);
        let r = self.decoders.sdf_residual(feat, Self::w(&s.geo, ng - 2));
        let [b, n, _] = r.dims();
        r.reshape([b, n])
    }

    /// Colours `[B, N, 3]` in [0, 1] at canonical points.
    pub fn texture_field(&self, planes: &Triplanes, s: &Styles, points: Tensor<3>) -> Tensor<3> {
        let (_, nt) = self.num_ws();
        let mut feat = sample_triplanes(planes.texture.clone(), points.clone());
        if let Some(face) = &self.face {
            feat = feat + face.features(points, Self::w(&s.tex, nt - 3));
        }
        self.decoders.rgb(feat, Self::w(&s.tex, nt - 1))
    }
}
