//! `trainer garment-codes`: the geometry codes of W+ inversions (`trainer invert` folders)
//! added to an encoder file as its garment codes
//! ([`getavatar_core::reconstruction::garment_codes`]), replacing any it had.

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use getavatar_core::generator::checkpoint::{parse_safetensors, write_safetensors, INVERTED_GEO};
use getavatar_core::reconstruction::encoder::ENCODER_FORMAT;
use getavatar_core::reconstruction::garment_codes::GARMENT_PREFIX;

use crate::atomic::write_atomic;

#[derive(clap::Args, Debug)]
pub struct GarmentCodesArgs {
    /// The encoder file the codes are added to.
    #[arg(long, default_value = "assets/models/encoder.safetensors")]
    pub encoder: PathBuf,
    /// `trainer invert` output folders (or their `inverted.safetensors`); each code is named
    /// after its folder.
    #[arg(long = "from", required = true, num_args = 1..)]
    pub from: Vec<PathBuf>,
    /// The encoder file written (may be --encoder itself).
    #[arg(long)]
    pub out: PathBuf,
}

pub fn garment_codes(a: &GarmentCodesArgs) -> Result<()> {
    let bytes = std::fs::read(&a.encoder).with_context(|| format!("reading {}", a.encoder.display()))?;
    let st = parse_safetensors(&bytes).with_context(|| format!("reading {}", a.encoder.display()))?;
    if st.metadata.get("format").map(String::as_str) != Some(ENCODER_FORMAT) {
        bail!("{} is not an encoder file (format `{ENCODER_FORMAT}`)", a.encoder.display());
    }
    let mut tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)> =
        st.tensors.into_iter().filter(|(k, _)| !k.starts_with(GARMENT_PREFIX)).collect();
    let mut shape: Option<Vec<usize>> = None;
    for dir in &a.from {
        let file = if dir.is_dir() { dir.join("inverted.safetensors") } else { dir.clone() };
        let name = if dir.is_dir() { dir.file_name() } else { dir.parent().and_then(|p| p.file_name()) }
            .and_then(|n| n.to_str())
            .with_context(|| format!("{}: no folder name to name the code by", dir.display()))?
            .to_string();
        let inv = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
        let inv = parse_safetensors(&inv).with_context(|| format!("reading {}", file.display()))?;
        let (s, v) = inv
            .tensors
            .get(INVERTED_GEO)
            .with_context(|| format!("{} has no geometry codes `{INVERTED_GEO}`", file.display()))?;
        if let Some(first) = shape.as_ref().filter(|first| *first != s) {
            bail!("{}: codes of shape {s:?}, the first were {first:?}", file.display());
        }
        shape = Some(s.clone());
        if tensors.insert(format!("{GARMENT_PREFIX}{name}"), (s.clone(), v.clone())).is_some() {
            bail!("two folders are named `{name}`");
        }
    }
    let named: Vec<(String, Vec<usize>, Vec<f32>)> = tensors.into_iter().map(|(k, (s, v))| (k, s, v)).collect();
    write_atomic(&a.out, &write_safetensors(&st.metadata, &named)?)?;
    println!("wrote {} with {} garment codes", a.out.display(), a.from.len());
    Ok(())
}
