//! Single-image reconstruction (paper Sec. 5.4): the generator's latent codes optimised so its
//! avatar, rendered at the photo's camera and fitted body pose, matches the photo; then pivotal
//! tuning (PTI, Roich et al. 2022) of the synthesis weights with the codes fixed.
//!
//! **Phase 1, W+ inversion.** Both branches' per-layer styles (`[1, n, w_dim]` each, W+) are
//! optimised by Adam (β = 0.9, 0.999) at `lr` with StyleGAN2's projector schedule (linear
//! warm-up over the first `warmup` of the steps, cosine ramp-down over the last `rampdown`).
//! The authors' script optimises Z+ for the texture only; here the geometry moves too (a
//! photo's clothes are not the template's), and the codes are W+ for both, held near their
//! start by `latent_reg · ‖w − w₀‖²` (mean over layers and dimensions). The start is the
//! checkpoint's latent mode (or w_avg) whose render explains the photo best ([`choose_start_async`]).
//!
//! **Phase 2, PTI.** The codes are frozen (the pivot); the synthesis backbone and decoders (not
//! the mapping networks) are tuned by Adam at `pti_lr` on the same image terms (constant by
//! default; with `pti_warmup`/`pti_rampdown` on the same schedule as phase 1), the texture
//! branch at `pti_texture_lr_mul` times that rate (both presets: 10). PTI's locality
//! regulariser keeps the rest of the latent space: every `locality_every` steps a random code
//! `w_z` of each branch is pulled towards the pivot, `w_r = w_p + (w_z − w_p)·min(1, α/‖w_z −
//! w_p‖)`, and the tuned generator's render there is held to the original's (L2 + perceptual).
//!
//! **Terms** at the photo's camera, images in [−1, 1] as the discriminators see them
//! ([`crate::render::diff::avatar`]): masked RGB L1 + MSE (inside the person mask only: the photo's
//! background is not the renderer's), the silhouette (squared error of the antialiased mask vs
//! the person mask), a perceptual term, and the paper's eikonal and SDF cross-entropy
//! regularisers.
//!
//! **Perceptual term.** Every reference recipe downloads ImageNet VGG16 (LPIPS), impossible
//! here; random-weight networks are no substitute (LPIPS paper). As Deep Generative Prior's
//! `DiscriminatorLoss` does, the term is the L1 distance between multi-scale features of a
//! trained discriminator ([`Discriminator::features`]), the checkpoint's RGB discriminator,
//! both images composed on white with the person mask. Without a discriminator the term is
//! off and the report says so.
//!
//! The same code runs natively and in the browser: every read-back is awaited
//! ([`Inverter::step_async`]); natively [`Inverter::step`] runs it to completion at once.
//!
//! - [`target`]: the photo at its camera and pose, the options and presets
//! - [`inverter`]: the optimiser (W+, then PTI), step by step
//! - [`start`]: the encoder's guess or the best latent mode
//! - [`figures`]: IoU, PSNR, the comparison strip

mod figures;
mod inverter;
mod start;
mod target;

pub use figures::*;
pub use inverter::*;
pub use start::*;
pub use target::*;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedule_warms_up_holds_and_ramps_down() {
        let f = |s| lr_schedule(0.1, s, 200, 0.05, 0.25);
        assert!(f(0) < 0.01, "{}", f(0));
        assert!(f(4) < f(9) && f(9) < 0.1 + 1e-6);
        assert!((f(50) - 0.1).abs() < 1e-6 && (f(140) - 0.1).abs() < 1e-6);
        assert!(f(170) < 0.1 && f(199) < 0.001 && f(199) > 0.0, "{} {}", f(170), f(199));
        // A short run warms up over 10 steps all the same: its first step is small.
        let short = |s| lr_schedule(0.1, s, 3, 0.05, 0.25);
        assert!(short(0) < 0.006 && short(1) > short(0) && short(1) < 0.02, "{} {}", short(0), short(1));
        // No warm-up and no ramp-down (PTI in `full`): the rate is constant.
        assert!((0..350).all(|s| lr_schedule(3e-4, s, 350, 0.0, 0.0) == 3e-4));
    }

    #[test]
    fn psnr_of_known_error() {
        let a = vec![0.5f32; 12];
        let b = vec![0.6f32; 12];
        let p = masked_psnr(&a, &b, &[1.0; 4]);
        assert!((p - 20.0).abs() < 1e-3, "{p}");
        // Pixels outside the mask do not count.
        let mut c = b.clone();
        c[0] = 0.0;
        assert!((masked_psnr(&a, &c, &[0.0, 1.0, 1.0, 1.0]) - 20.0).abs() < 1e-3);
    }
}
