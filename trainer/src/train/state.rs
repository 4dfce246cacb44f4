//! The training state (`state.safetensors`): G, G_ema, the three discriminators, Adam
//! moments, step and RNG state. A resumed run continues bit-identically on the same backend.

use std::collections::BTreeMap;

use anyhow::{anyhow, bail, Result};
use getavatar_core::burn::tensor::Device;
use getavatar_core::generator::checkpoint::{collect_params, load_params, parse_safetensors, write_safetensors};
use getavatar_core::generator::network::discriminator::Discriminator;
use getavatar_core::generator::optim::Adam;
use getavatar_core::generator::pipeline::Generator;
use getavatar_core::util::rng::Rng;

use super::run_config::{Objective, RunConfig};
use super::subject_codes::SubjectCodes;

const STATE_FORMAT: &str = "getavatar-train-state/1";

/// Everything that changes during training.
pub struct State {
    pub g: Generator,
    pub g_ema: Generator,
    /// RGB, normal, mask.
    pub d: Vec<Discriminator>,
    pub adam_g: Adam,
    pub adam_d: Vec<Adam>,
    /// The learned subject codes of a reconstruction run with `lr_codes` > 0, their moving
    /// average beside G_ema (on its device), and their Adam.
    pub codes: Option<SubjectCodes>,
    pub codes_ema: Option<SubjectCodes>,
    pub adam_codes: Adam,
    pub step: u64,
    pub rng: Rng,
}

/// G's optimiser: the paper's Adam β = (0, 0.99) for the adversarial game; β₁ = 0.9 (momentum)
/// for the reconstruction warm-up, whose L1 gradients are noisy per batch but not adversarial.
pub(crate) fn generator_adam(rc: &RunConfig) -> Adam {
    match rc.objective {
        Objective::Adversarial => Adam::new(0.0, 0.99, 1e-8),
        Objective::Reconstruction => Adam::new(0.9, 0.99, 1e-8),
    }
}

impl State {
    pub fn new(rc: &RunConfig, ad: &Device, plain: &Device) -> Self {
        let seed = rc.seed;
        Self {
            g: Generator::new(&rc.generator, seed, ad),
            g_ema: Generator::new(&rc.generator, seed, plain),
            d: [3usize, 3, 1]
                .iter()
                .enumerate()
                .map(|(k, &c)| Discriminator::new(&rc.discriminator, c, seed + 100 + k as u64, ad))
                .collect(),
            adam_g: generator_adam(rc),
            adam_d: (0..3).map(|_| Adam::new(0.0, 0.99, 1e-8)).collect(),
            codes: None,
            codes_ema: None,
            adam_codes: generator_adam(rc),
            step: 0,
            rng: Rng::new(seed, 0x7a1e),
        }
    }

    pub fn save(&self, rc: &RunConfig) -> Result<Vec<u8>> {
        let mut tensors = Vec::new();
        let mut put = |prefix: &str, v: Vec<(String, Vec<usize>, Vec<f32>)>| {
            tensors.extend(v.into_iter().map(|(n, s, d)| (format!("{prefix}{n}"), s, d)));
        };
        put("g/", collect_params(&self.g)?);
        put("g_ema/", collect_params(&self.g_ema)?);
        for (k, d) in self.d.iter().enumerate() {
            put(&format!("d{k}/"), collect_params(d)?);
        }
        if let Some(c) = &self.codes {
            put("codes/", collect_params(c)?);
        }
        if let Some(c) = &self.codes_ema {
            put("codes_ema/", collect_params(c)?);
        }
        let adams: Vec<(String, &Adam)> = std::iter::once(("adam_g/".to_string(), &self.adam_g))
            .chain(self.adam_d.iter().enumerate().map(|(k, a)| (format!("adam_d{k}/"), a)))
            .chain(self.codes.is_some().then(|| ("adam_codes/".to_string(), &self.adam_codes)))
            .collect();
        let mut meta = BTreeMap::new();
        for (prefix, a) in &adams {
            tensors.extend(a.moment_tensors(prefix)?);
            meta.insert(format!("{prefix}step"), a.step.to_string());
        }
        let (s, inc) = self.rng.state();
        meta.insert("format".into(), STATE_FORMAT.into());
        meta.insert("step".into(), self.step.to_string());
        meta.insert("rng_state".into(), s.to_string());
        meta.insert("rng_inc".into(), inc.to_string());
        meta.insert("run".into(), serde_json::to_string(rc)?);
        Ok(write_safetensors(&meta, &tensors)?)
    }

    /// The step a saved state was taken at (read from its metadata alone).
    pub fn step_of(bytes: &[u8]) -> Result<u64> {
        let st = parse_safetensors(bytes)?;
        st.metadata.get("step").and_then(|v| v.parse().ok()).ok_or_else(|| anyhow!("state metadata lacks `step`"))
    }

    pub fn load(bytes: &[u8], rc: &RunConfig, ad: &Device, plain: &Device) -> Result<Self> {
        let st = parse_safetensors(bytes)?;
        if st.metadata.get("format").map(String::as_str) != Some(STATE_FORMAT) {
            bail!("not a training state (format {:?})", st.metadata.get("format"));
        }
        let num = |k: &str| -> Result<u64> {
            st.metadata.get(k).and_then(|v| v.parse().ok()).ok_or_else(|| anyhow!("state metadata lacks `{k}`"))
        };
        let mut s = State::new(rc, ad, plain);
        s.g = load_params(s.g, &st.tensors, "g/", ad)?;
        s.g_ema = load_params(s.g_ema, &st.tensors, "g_ema/", plain)?;
        s.d =
            s.d.into_iter()
                .enumerate()
                .map(|(k, d)| load_params(d, &st.tensors, &format!("d{k}/"), ad))
                .collect::<Result<_, _>>()?;
        let inner = ad.clone().without_autodiff();
        if let Some((shape, _)) = st.tensors.get("codes/geo") {
            let [n, w] = shape[..] else { bail!("codes/geo has shape {shape:?}, expected [subjects, w_dim]") };
            // W codes: `[n, w]`; W+ texture codes: `[n, layers · w]`.
            let layers = match st.tensors.get("codes/tex").map(|(s, _)| &s[..]) {
                Some(&[m, k]) if m == n && k % w == 0 && k > 0 => k / w,
                other => bail!("codes/tex has shape {other:?}, expected [{n}, layers · {w}]"),
            };
            let codes = load_params(SubjectCodes::zeros(n, w, layers, ad), &st.tensors, "codes/", ad)?;
            s.codes_ema = Some(if st.tensors.contains_key("codes_ema/geo") {
                load_params(SubjectCodes::zeros(n, w, layers, plain), &st.tensors, "codes_ema/", plain)?
            } else {
                codes.copy_to(plain)?
            });
            s.codes = Some(codes);
        }
        // `fresh`: the optimiser as a new run makes it (its betas), to fill with the moments.
        let load_adam = |prefix: &str, fresh: Adam| -> Result<Adam> {
            let mut a = fresh.with_moments(&st.tensors, prefix, &inner).map_err(|e| anyhow!("state {e}"))?;
            a.step = num(&format!("{prefix}step"))?;
            Ok(a)
        };
        s.adam_g = load_adam("adam_g/", generator_adam(rc))?;
        s.adam_d =
            (0..3).map(|k| load_adam(&format!("adam_d{k}/"), Adam::new(0.0, 0.99, 1e-8))).collect::<Result<_>>()?;
        if s.codes.is_some() {
            s.adam_codes = load_adam("adam_codes/", generator_adam(rc))?;
        }
        s.step = num("step")?;
        s.rng = Rng::from_state(num("rng_state")?, num("rng_inc")?);
        Ok(s)
    }
}
