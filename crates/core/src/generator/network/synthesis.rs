//! Triplane synthesis (paper Sec. 4.1): a StyleGAN2 "skip" backbone from 4² to `plane_res`²
//! whose 3×3 modulated convolutions are driven by w_geo only; every block has two 1×1
//! modulated output layers without demodulation: "to-geometry" (styled by w_geo) and
//! "to-texture" (styled by w_tex). Their outputs are upsampled and summed across blocks,
//! giving 3 geometry planes and 3 texture planes of `plane_channels` channels.
//!
//! Upsampling is 2× bilinear with half-pixel centres, written with basic tensor ops so it is
//! differentiable on every backend (StyleGAN2 uses a transposed convolution with an FIR filter).

use burn::module::{Module, Param};
use burn::tensor::{Device, Int, Tensor, TensorData};

use super::config::GeneratorConfig;
use super::init::{randn, Rng};
use super::layers::ModulatedConv2d;

/// 2× bilinear upsampling along dimension `dim` (2 = rows, 3 = columns), half-pixel centres,
/// edges clamped: `out[2i] = ¾x[i] + ¼x[i−1]`, `out[2i+1] = ¾x[i] + ¼x[i+1]`.
///
/// Without gradients (generation), two row gathers (`select`) straight into the upsampled
/// size: a dimension costs five GPU launches (two gathers, two scalings, one sum) instead of
/// the slicing, concatenating and interleaving of [`upsample_dim_by_slices`] (
/// launches are what a GPU waits on here). The values are the same bits (same products, same
/// sum). Training and inversion keep the sliced version: the gathers' backward is a
/// scatter-add whose rounding differs, which changed the inversion's trajectories. burn's
/// bilinear `interpolate` has no backward pass on NdArray.
fn upsample_dim(x: Tensor<4>, dim: usize) -> Tensor<4> {
    #[cfg(feature = "autodiff")]
    if x.is_tracked() {
        return upsample_dim_by_slices(x, dim);
    }
    let n = x.dims()[dim];
    let device = x.device();
    let (own, neighbour): (Vec<i64>, Vec<i64>) = (0..2 * n as i64)
        .map(|k| {
            let i = k / 2;
            let j = if k % 2 == 0 { (i - 1).max(0) } else { (i + 1).min(n as i64 - 1) };
            (i, j)
        })
        .unzip();
    let index = |v: Vec<i64>| Tensor::<1, Int>::from_data(TensorData::new(v, [2 * n]), &device);
    x.clone().select(dim, index(own)) * 0.75 + x.select(dim, index(neighbour)) * 0.25
}

/// [`upsample_dim`] by slicing, concatenating and interleaving (what gradients go through).
fn upsample_dim_by_slices(x: Tensor<4>, dim: usize) -> Tensor<4> {
    let dims = x.dims();
    let n = dims[dim];
    let (prev, next) = if n > 1 {
        (
            Tensor::cat(vec![x.clone().narrow(dim, 0, 1), x.clone().narrow(dim, 0, n - 1)], dim),
            Tensor::cat(vec![x.clone().narrow(dim, 1, n - 1), x.clone().narrow(dim, n - 1, 1)], dim),
        )
    } else {
        (x.clone(), x.clone())
    };
    let even = x.clone() * 0.75 + prev * 0.25;
    let odd = x * 0.75 + next * 0.25;
    let both: Tensor<5> = Tensor::cat(vec![even.unsqueeze_dim(dim + 1), odd.unsqueeze_dim(dim + 1)], dim + 1);
    let mut out = dims;
    out[dim] = 2 * n;
    both.reshape(out)
}

fn upsample2(x: Tensor<4>) -> Tensor<4> {
    #[cfg(feature = "wgpu")]
    if let Some(y) = super::cube_ops::upsample2(&x, None) {
        return y;
    }
    // One operation each way on the CPU (`ndarray_ops`): the same values as the tensor ops
    // below, without their copies.
    #[cfg(feature = "ndarray")]
    if super::layers::is_ndarray(&x.device()) {
        return super::ndarray_ops::upsample2(x);
    }
    upsample_dim(upsample_dim(x, 2), 3)
}

/// `upsample2(x) + skip`: one kernel on wgpu for generation ([`super::cube_ops`]).
fn upsample2_add(x: Tensor<4>, skip: Tensor<4>) -> Tensor<4> {
    #[cfg(feature = "wgpu")]
    if let Some(y) = super::cube_ops::upsample2(&x, Some(&skip)) {
        return y;
    }
    upsample2(x) + skip
}

#[derive(Module, Debug)]
pub struct SynthesisBlock {
    /// Learned constant input (first block only): `[C, 4, 4]`.
    pub constant: Option<Param<Tensor<3>>>,
    /// 3×3 convs (one in the first block, two after upsampling in the others).
    pub convs: Vec<ModulatedConv2d>,
    pub to_geometry: ModulatedConv2d,
    pub to_texture: ModulatedConv2d,
    pub res: usize,
}

/// Output of the backbone: geometry and texture triplanes, each `[B, 3·C, R, R]`.
#[derive(Clone, Debug)]
pub struct Triplanes {
    pub geometry: Tensor<4>,
    pub texture: Tensor<4>,
}

/// A texture-only block after the backbone (not in the paper; `GeneratorConfig::texture_res`):
/// the backbone's last features upsampled 2× and, beside them, a learned constant at the
/// block's resolution; one 3×3 modulated conv and a to-texture layer, both styled by w_tex,
/// added to the 2×-upsampled texture planes. Its to-texture layer starts at zero, so a grown
/// generator renders what it rendered before, with planes that can now hold detail at half
/// the texel size.
///
/// The constant is what makes that detail learnable: the upsampled features are smooth, and a
/// conv of smooth features learns a high-frequency target (stripes, a face's features) only
/// slowly (a single subject's stripes stayed averaged after 250 steps without it). The L1
/// gradient reaches the constant directly, as a free field in canonical plane space shared by
/// all identities (a face sits at the same canonical place on every body), which each
/// identity's w_tex weighs through the modulated conv (as CIPS's and StyleGAN3's spatial
/// inputs do).
#[derive(Module, Debug)]
pub struct TextureDetailBlock {
    /// `[C, res, res]`, concatenated to the upsampled features.
    pub constant: Param<Tensor<3>>,
    pub conv: ModulatedConv2d,
    pub to_texture: ModulatedConv2d,
    pub res: usize,
}

impl TextureDetailBlock {
    pub fn new(rng: &mut Rng, cfg: &GeneratorConfig, c_in: usize, res: usize, device: &Device) -> Self {
        let c = cfg.channels(res);
        let constant = Param::from_tensor(randn(rng, [c, res, res], 1.0, device));
        let conv = ModulatedConv2d::new(rng, cfg.w_dim, c_in + c, c, 3, true, true, device);
        let mut to_texture = ModulatedConv2d::new(rng, cfg.w_dim, c, 3 * cfg.plane_channels, 1, false, false, device);
        to_texture.weight = Param::from_tensor(to_texture.weight.val().zeros_like());
        Self { constant, conv, to_texture, res }
    }
}

/// A geometry-only block after the backbone (not in the paper; `GeneratorConfig::geometry_res`),
/// the texture detail block's twin for the SDF-residual planes: the backbone's last features
/// (or the previous geometry block's) upsampled 2× beside a learned constant, one 3×3
/// modulated conv and a to-geometry layer styled by w_geo, added to the 2×-upsampled geometry
/// planes. Its to-geometry layer starts at zero, so a grown generator's SDF is the saved one's
/// up to that upsampling. The constant is a free field in canonical plane space shared by all
/// identities: surface detail that sits at the same canonical place on every body (a face's
/// relief) is learnt once and weighed per identity; detail that moves with the body's shape
/// (garment folds) has to come from w_geo through the conv (MODEL_CARD, Evaluation: normal error).
#[derive(Module, Debug)]
pub struct GeometryDetailBlock {
    /// `[C, res, res]`, concatenated to the upsampled features.
    pub constant: Param<Tensor<3>>,
    pub conv: ModulatedConv2d,
    pub to_geometry: ModulatedConv2d,
    pub res: usize,
}

impl GeometryDetailBlock {
    pub fn new(rng: &mut Rng, cfg: &GeneratorConfig, c_in: usize, res: usize, device: &Device) -> Self {
        let TextureDetailBlock { constant, conv, to_texture, res } =
            TextureDetailBlock::new(rng, cfg, c_in, res, device);
        Self { constant, conv, to_geometry: to_texture, res }
    }
}

#[derive(Module, Debug)]
pub struct TriplaneSynthesis {
    pub blocks: Vec<SynthesisBlock>,
    /// Texture-only blocks beyond `plane_res` (empty in the paper's configs).
    pub texture_detail: Vec<TextureDetailBlock>,
    /// Geometry-only blocks beyond `plane_res` (empty in the paper's configs).
    pub geometry_detail: Vec<GeometryDetailBlock>,
}

impl TriplaneSynthesis {
    pub fn new(rng: &mut Rng, cfg: &GeneratorConfig, device: &Device) -> Self {
        let out = 3 * cfg.plane_channels;
        let mut blocks = Vec::new();
        let mut c_prev = 0;
        for res in cfg.block_resolutions() {
            let c = cfg.channels(res);
            let (constant, convs) = if res == 4 {
                (
                    Some(Param::from_tensor(randn(rng, [c, 4, 4], 1.0, device))),
                    vec![ModulatedConv2d::new(rng, cfg.w_dim, c, c, 3, true, true, device)],
                )
            } else {
                (
                    None,
                    vec![
                        ModulatedConv2d::new(rng, cfg.w_dim, c_prev, c, 3, true, true, device),
                        ModulatedConv2d::new(rng, cfg.w_dim, c, c, 3, true, true, device),
                    ],
                )
            };
            let to_geometry = ModulatedConv2d::new(rng, cfg.w_dim, c, out, 1, false, false, device);
            let to_texture = ModulatedConv2d::new(rng, cfg.w_dim, c, out, 1, false, false, device);
            blocks.push(SynthesisBlock { constant, convs, to_geometry, to_texture, res });
            c_prev = c;
        }
        let backbone_channels = c_prev;
        // Drawn after the backbone's (texture, then geometry): configs without detail blocks
        // initialise as before, and so do those without geometry detail.
        let texture_detail = cfg
            .texture_detail_resolutions()
            .into_iter()
            .map(|res| {
                let block = TextureDetailBlock::new(rng, cfg, c_prev, res, device);
                c_prev = cfg.channels(res);
                block
            })
            .collect();
        let mut c_prev = backbone_channels;
        let geometry_detail = cfg
            .geometry_detail_resolutions()
            .into_iter()
            .map(|res| {
                let block = GeometryDetailBlock::new(rng, cfg, c_prev, res, device);
                c_prev = cfg.channels(res);
                block
            })
            .collect();
        Self { blocks, texture_detail, geometry_detail }
    }

    /// Number of w_geo vectors consumed (one per 3×3 conv and per to-geometry layer, and per
    /// geometry detail conv).
    pub fn num_ws_geo(&self) -> usize {
        self.blocks.iter().map(|b| b.convs.len() + 1).sum::<usize>() + 2 * self.geometry_detail.len()
    }

    /// Number of w_tex vectors consumed (one per to-texture layer, and per detail conv).
    pub fn num_ws_tex(&self) -> usize {
        self.blocks.len() + 2 * self.texture_detail.len()
    }

    /// `ws_geo`: `[B, num_ws_geo, w_dim]`, `ws_tex`: `[B, num_ws_tex, w_dim]` (W+; repeat one w
    /// for the usual W space).
    pub fn forward(&self, ws_geo: Tensor<3>, ws_tex: Tensor<3>) -> Triplanes {
        let mut state = SynthesisState::default();
        for block in &self.blocks {
            state.run(block, &ws_geo, &ws_tex);
        }
        let backbone = state.x.clone();
        for block in &self.texture_detail {
            state.detail(block, &ws_tex);
        }
        state.x = backbone;
        for block in &self.geometry_detail {
            state.geometry_detail(block, &ws_geo);
        }
        state.finish()
    }

    /// [`TriplaneSynthesis::forward`] with a checkpoint (`cooperative`) after each block: in
    /// the browser, launching a whole backbone's kernels at once held the UI thread ~100 ms.
    pub async fn forward_async(&self, ws_geo: Tensor<3>, ws_tex: Tensor<3>) -> Triplanes {
        let mut state = SynthesisState::default();
        for block in &self.blocks {
            state.run(block, &ws_geo, &ws_tex);
            crate::util::cooperative::checkpoint().await;
        }
        let backbone = state.x.clone();
        for block in &self.texture_detail {
            state.detail(block, &ws_tex);
            crate::util::cooperative::checkpoint().await;
        }
        state.x = backbone;
        for block in &self.geometry_detail {
            state.geometry_detail(block, &ws_geo);
            crate::util::cooperative::checkpoint().await;
        }
        state.finish()
    }
}

impl TriplaneSynthesis {
    /// The geometry planes alone: the backbone without its texture outputs, then the geometry
    /// detail blocks (what the SDF and the DMTet offsets read; the same values as
    /// [`TriplaneSynthesis::forward_async`]'s). With a checkpoint after each block.
    pub async fn forward_geometry_async(&self, ws_geo: Tensor<3>) -> Tensor<4> {
        let mut state = SynthesisState { geometry_only: true, ..SynthesisState::default() };
        for block in &self.blocks {
            state.run(block, &ws_geo, &ws_geo);
            crate::util::cooperative::checkpoint().await;
        }
        for block in &self.geometry_detail {
            state.geometry_detail(block, &ws_geo);
            crate::util::cooperative::checkpoint().await;
        }
        state.geo.unwrap_or_else(|| unreachable_input())
    }
}

/// The backbone's running state between blocks: features, the two accumulated skip outputs,
/// and how many w codes each branch has consumed; with `geometry_only`, no texture output.
#[derive(Default)]
struct SynthesisState {
    x: Option<Tensor<4>>,
    geo: Option<Tensor<4>>,
    tex: Option<Tensor<4>>,
    gi: usize,
    ti: usize,
    geometry_only: bool,
}

impl SynthesisState {
    fn run(&mut self, block: &SynthesisBlock, ws_geo: &Tensor<3>, ws_tex: &Tensor<3>) {
        let [b, _, w_dim] = ws_geo.dims();
        let pick = |ws: &Tensor<3>, i: usize| ws.clone().narrow(1, i, 1).reshape([b, w_dim]);
        let mut h = match (&block.constant, self.x.take()) {
            (Some(c), _) => {
                let [ch, r, _] = c.dims();
                c.val().unsqueeze_dim::<4>(0).expand([b, ch, r, r])
            }
            (None, Some(prev)) => upsample2(prev),
            (None, None) => unreachable_input(),
        };
        for conv in &block.convs {
            h = conv.forward(h, pick(ws_geo, self.gi));
            self.gi += 1;
        }
        let g = block.to_geometry.forward(h.clone(), pick(ws_geo, self.gi));
        self.gi += 1;
        self.geo = Some(match self.geo.take() {
            Some(prev) => upsample2_add(prev, g),
            None => g,
        });
        if !self.geometry_only {
            let t = block.to_texture.forward(h.clone(), pick(ws_tex, self.ti));
            self.tex = Some(match self.tex.take() {
                Some(prev) => upsample2_add(prev, t),
                None => t,
            });
        }
        self.ti += 1;
        self.x = Some(h);
    }

    /// A texture detail block: features and texture planes carried on at twice the size.
    fn detail(&mut self, block: &TextureDetailBlock, ws_tex: &Tensor<3>) {
        let (Some(x), Some(tex)) = (self.x.take(), self.tex.take()) else { unreachable_input() };
        let (h, tex) = detail_step(&block.constant, &block.conv, &block.to_texture, x, tex, ws_tex, self.ti);
        self.ti += 2;
        self.tex = Some(tex);
        self.x = Some(h);
    }

    /// A geometry detail block: features (from the backbone's last block on) and geometry
    /// planes carried on at twice the size.
    fn geometry_detail(&mut self, block: &GeometryDetailBlock, ws_geo: &Tensor<3>) {
        let (Some(x), Some(geo)) = (self.x.take(), self.geo.take()) else { unreachable_input() };
        let (h, geo) = detail_step(&block.constant, &block.conv, &block.to_geometry, x, geo, ws_geo, self.gi);
        self.gi += 2;
        self.geo = Some(geo);
        self.x = Some(h);
    }

    fn finish(self) -> Triplanes {
        match (self.geo, self.tex) {
            (Some(geometry), Some(texture)) => Triplanes { geometry, texture },
            _ => unreachable_input(),
        }
    }
}

/// One detail block (texture or geometry): the features `x` upsampled 2× beside the block's
/// `constant`, its `conv` styled by `ws[i]` and its output layer `out` by `ws[i + 1]`; returns
/// the block's features and `planes` upsampled 2× plus the output.
#[allow(clippy::too_many_arguments)]
fn detail_step(
    constant: &Param<Tensor<3>>,
    conv: &ModulatedConv2d,
    out: &ModulatedConv2d,
    x: Tensor<4>,
    planes: Tensor<4>,
    ws: &Tensor<3>,
    i: usize,
) -> (Tensor<4>, Tensor<4>) {
    let [b, _, w_dim] = ws.dims();
    let pick = |i: usize| ws.clone().narrow(1, i, 1).reshape([b, w_dim]);
    let [ch, r, _] = constant.dims();
    let constant = constant.val().unsqueeze_dim::<4>(0).expand([b, ch, r, r]);
    let h = conv.forward(Tensor::cat(vec![upsample2(x), constant], 1), pick(i));
    let o = out.forward(h.clone(), pick(i + 1));
    (h, upsample2_add(planes, o))
}

/// The backbone always has at least the 4² block; reaching this is a construction bug.
fn unreachable_input() -> ! {
    unreachable!("triplane synthesis has no blocks")
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::TensorData;

    #[test]
    fn upsampling_is_half_pixel_bilinear() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let x = Tensor::<4>::from_data(TensorData::new(vec![0.0f32, 4.0, 8.0, 12.0], [1, 1, 2, 2]), &dev);
        let y = upsample2(x).into_data().try_to_vec::<f32>().unwrap();
        // Row 0 of the input is [0, 4] → [0, 1, 3, 4]; the first output row blends ¾ row 0 + ¼ row 0.
        assert_eq!(&y[..4], &[0.0, 1.0, 3.0, 4.0]);
        // Output row 1 = ¾·row 0 + ¼·row 1 = [2, 6] → [2, 3, 5, 6].
        assert_eq!(&y[4..8], &[2.0, 3.0, 5.0, 6.0]);
        assert_eq!(y.len(), 16);
    }

    /// The NdArray operation (`ndarray_ops::upsample2`) against the tensor-op path it
    /// replaces on the CPU: the same bits forward, and under autodiff the same gradient.
    #[cfg(all(feature = "autodiff", feature = "ndarray"))]
    #[test]
    fn the_cpu_upsampling_operation_equals_the_tensor_ops_and_so_do_its_gradients() {
        #[allow(deprecated)]
        let dev = Device::ndarray().autodiff();
        let vals: Vec<f32> = (0..2 * 3 * 5 * 7).map(|i| ((i * 7919 % 1013) as f32 - 500.0) * 0.0137).collect();
        let weights: Vec<f32> = (0..2 * 3 * 10 * 14).map(|i| ((i * 104_729 % 997) as f32 - 498.0) * 0.01).collect();
        let wt = Tensor::<4>::from_data(TensorData::new(weights, [2, 3, 10, 14]), &dev);
        let run = |op: bool| {
            let x = Tensor::<4>::from_data(TensorData::new(vals.clone(), [2, 3, 5, 7]), &dev).require_grad();
            let y = if op {
                crate::generator::network::ndarray_ops::upsample2(x.clone())
            } else {
                upsample_dim(upsample_dim(x.clone(), 2), 3)
            };
            let grads = (y.clone() * wt.clone()).sum().backward();
            let g = x.grad(&grads).expect("x is tracked").into_data().try_to_vec::<f32>().unwrap();
            (y.into_data().try_to_vec::<f32>().unwrap(), g)
        };
        let ((y_op, g_op), (y_ref, g_ref)) = (run(true), run(false));
        assert_eq!(y_op, y_ref);
        for (a, b) in g_op.iter().zip(&g_ref) {
            assert!((a - b).abs() <= 1e-5 * b.abs().max(1.0), "{a} vs {b}");
        }
    }

    #[test]
    fn gathered_upsampling_equals_the_sliced_one_bit_for_bit() {
        #[allow(deprecated)]
        let dev = Device::ndarray();
        let vals: Vec<f32> = (0..2 * 3 * 5 * 7).map(|i| ((i * 7919 % 1013) as f32 - 500.0) * 0.0137).collect();
        let x0 = Tensor::<4>::from_data(TensorData::new(vals, [2, 3, 5, 7]), &dev);
        // Contiguous, transposed and narrowed inputs, each dimension, and a size-1 dimension.
        for x in [x0.clone(), x0.clone().swap_dims(2, 3), x0.clone().narrow(3, 1, 5), x0.narrow(2, 0, 1)] {
            for dim in [2, 3] {
                let a = upsample_dim(x.clone(), dim).into_data().try_to_vec::<f32>().unwrap();
                let b = upsample_dim_by_slices(x.clone(), dim).into_data().try_to_vec::<f32>().unwrap();
                assert_eq!(a, b, "dim {dim}, input {:?}", x.dims());
            }
        }
    }
}
