//! The body context as one file's bytes, for keeping it between processes: the template SDF
//! and the canonical pose's posed grid ([`BodyContext`]), which every command that generates
//! needs and which cost about 0.7 s of a 2-core machine's time before each first avatar
//! natively, 3–4 s in the browser's reconstruction worker. The bytes hold them bit for bit as
//! computed; the tet grid (regular, 0.2 s) is rebuilt beside the parsing. Where the bytes live
//! is the caller's: a file written atomically (`trainer`'s `model_io::body_context`), the
//! browser's Cache API (the web crate's `reconstruct::kept_context`).
//!
//! Each body and resolution has its own file name ([`file_name`]); the bytes carry a key over
//! the body, the resolutions and the source of the code that computes them ([`SOURCES`]), and
//! a checksum: bytes of another build, body or resolution, or damaged ones, are refused with
//! the reason ([`from_bytes`]), never used.

use glam::Vec3;

use super::inverse_skinning::canonical_body;
use super::posed_grid::{BodyContext, PosedGrid};
use super::template_sdf::TemplateSdf;
use super::tet_grid::TetGrid;
use crate::body::body_model::BodyModel;
use crate::body::skinning::PosedBody;
#[cfg(not(target_arch = "wasm32"))]
use crate::util::cooperative::run_blocking;

/// The first bytes of a cache file (the format's version in the last two).
const MAGIC: &[u8; 8] = b"GAVCTX01";

/// A hash of the code the cached values come from: any change to it makes every file stale.
/// Computed at compile time, so the source text stays out of the binary (the wasm module).
const SOURCES: u64 = {
    let sources = [
        include_str!("context_cache.rs"),
        include_str!("inverse_skinning.rs"),
        include_str!("posed_grid.rs"),
        include_str!("spatial.rs"),
        include_str!("template_sdf.rs"),
        include_str!("tet_grid.rs"),
    ];
    let mut h = Hasher::new();
    let mut k = 0;
    while k < sources.len() {
        h.bytes(sources[k].as_bytes());
        k += 1;
    }
    h.0
};

/// The file name of `model`'s context at `template_res` / `tet_res`.
pub fn file_name(model: &BodyModel, template_res: usize, tet_res: usize) -> String {
    format!("body-{:016x}-{template_res}-{tet_res}.bin", body_hash(model, &canonical_body(model)))
}

/// The context of `model` at `template_res` / `tet_res` from the bytes [`to_bytes`] made, its
/// canonical grid made; `Err`: why these bytes are not that context's.
pub fn from_bytes(model: BodyModel, bytes: &[u8], template_res: usize, tet_res: usize) -> Result<BodyContext, String> {
    let canonical = canonical_body(&model);
    let key = key(body_hash(&model, &canonical), template_res, tet_res);
    let tet_grid = || {
        let grid = TetGrid::reference(tet_res);
        let boundary = grid.boundary_flags();
        (grid, boundary)
    };
    // The tet grid is regular: natively built beside the parsing.
    #[cfg(not(target_arch = "wasm32"))]
    let (parsed, (grid, boundary)) = std::thread::scope(|sc| {
        let grid = sc.spawn(tet_grid);
        let parsed = parse(bytes, key, template_res, tet_res);
        (parsed, grid.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic)))
    });
    #[cfg(target_arch = "wasm32")]
    let (parsed, (grid, boundary)) = {
        let parsed = parse(bytes, key, template_res, tet_res);
        (parsed, tet_grid())
    };
    let (template, posed) = parsed?;
    Ok(BodyContext::assemble(model, canonical, template, grid, boundary).with_canonical_grid(posed))
}

/// `ctx` as bytes for [`from_bytes`]; `Err` when its canonical grid has not been made.
pub fn to_bytes(ctx: &BodyContext) -> Result<Vec<u8>, String> {
    let posed = ctx.canonical_grid_made().ok_or("the body context has no canonical grid yet")?;
    let key = key(body_hash(&ctx.model, &ctx.canonical), ctx.template.res, ctx.grid.res);
    Ok(serialize(key, &ctx.template, posed))
}

/// The body context built in this process, its canonical grid made: what [`from_bytes`]
/// gives from the bytes of one built before.
#[cfg(not(target_arch = "wasm32"))]
pub fn build(model: BodyModel, template_res: usize, tet_res: usize) -> BodyContext {
    let ctx = BodyContext::with_resolution(model, template_res, tet_res);
    run_blocking(ctx.canonical_grid_async(ctx.canonical_inverse()));
    ctx
}

/// A 64-bit hash of words (splitmix64's finaliser over each word folded in): a cache key and a
/// checksum, not a defence against a forger.
struct Hasher(u64);

impl Hasher {
    const fn new() -> Self {
        Self(0x9e37_79b9_7f4a_7c15)
    }

    const fn word(&mut self, w: u64) {
        let mut z = (self.0 ^ w).wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        self.0 = z ^ (z >> 31);
    }

    /// The bytes' length, then their 8-byte little-endian words, the last one zero-padded (a
    /// zero word when the length is a multiple of 8). A `const fn` for [`SOURCES`].
    const fn bytes(&mut self, b: &[u8]) {
        self.word(b.len() as u64);
        let mut at = 0;
        while at + 8 <= b.len() {
            let w = [b[at], b[at + 1], b[at + 2], b[at + 3], b[at + 4], b[at + 5], b[at + 6], b[at + 7]];
            self.word(u64::from_le_bytes(w));
            at += 8;
        }
        let mut last = [0u8; 8];
        let mut k = 0;
        while at + k < b.len() {
            last[k] = b[at + k];
            k += 1;
        }
        self.word(u64::from_le_bytes(last));
    }

    fn floats(&mut self, v: impl IntoIterator<Item = f32>) {
        for x in v {
            self.word(x.to_bits() as u64);
        }
    }
}

/// The body as the cached values see it: the canonical body's shape, pose and transforms and
/// the template's triangles.
fn body_hash(model: &BodyModel, canonical: &PosedBody) -> u64 {
    let mut h = Hasher::new();
    let v3 = |v: &[Vec3]| v.iter().flat_map(|p| p.to_array()).collect::<Vec<f32>>();
    h.floats(v3(&model.v_template));
    h.floats(v3(&canonical.shaped));
    h.floats(v3(&canonical.vertices));
    h.floats(canonical.vertex_transforms.iter().flat_map(|m| m.to_cols_array()));
    for f in &model.faces {
        h.word(((f[0] as u64) << 32) | f[1] as u64);
        h.word(f[2] as u64);
    }
    h.0
}

/// The key a file must carry: the body, the resolutions and the code.
fn key(body: u64, template_res: usize, tet_res: usize) -> u64 {
    let mut h = Hasher::new();
    h.bytes(MAGIC);
    h.word(body);
    h.word(template_res as u64);
    h.word(tet_res as u64);
    h.word(SOURCES);
    h.0
}

/// The file: magic, key, the template SDF (res, min, cell, values), the canonical grid
/// (vertex count, canonical points, template values, band), then the checksum of all before it.
fn serialize(key: u64, template: &TemplateSdf, posed: &PosedGrid) -> Vec<u8> {
    let n = posed.canonical.len();
    let mut out = Vec::with_capacity(64 + 4 * (template.values.len() + 4 * n + posed.band.len()));
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&key.to_le_bytes());
    out.extend_from_slice(&(template.res as u64).to_le_bytes());
    for x in template.min.to_array().into_iter().chain([template.cell]).chain(template.values.iter().copied()) {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out.extend_from_slice(&(n as u64).to_le_bytes());
    for x in posed.canonical.iter().flat_map(|p| p.to_array()).chain(posed.template.iter().copied()) {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out.extend_from_slice(&(posed.band.len() as u64).to_le_bytes());
    for i in &posed.band {
        out.extend_from_slice(&i.to_le_bytes());
    }
    let mut h = Hasher::new();
    h.bytes(&out);
    out.extend_from_slice(&h.0.to_le_bytes());
    out
}

/// Reads what [`serialize`] wrote, checking each part against what the caller needs.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or("the file ends early")?;
        let b = &self.bytes[self.at..end];
        self.at = end;
        Ok(b)
    }

    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().map_err(|_| "the file ends early")?))
    }

    fn count(&mut self, expected: usize, what: &str) -> Result<usize, String> {
        let n = self.u64()?;
        if n != expected as u64 {
            return Err(format!("{what}: {n} where this build needs {expected}"));
        }
        Ok(expected)
    }

    fn words(&mut self, n: usize) -> Result<impl Iterator<Item = [u8; 4]> + 'a, String> {
        let b = self.take(n.checked_mul(4).ok_or("a count overflows")?)?;
        Ok(b.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]))
    }

    fn f32s(&mut self, n: usize) -> Result<Vec<f32>, String> {
        Ok(self.words(n)?.map(f32::from_le_bytes).collect())
    }
}

fn parse(bytes: &[u8], key: u64, template_res: usize, tet_res: usize) -> Result<(TemplateSdf, PosedGrid), String> {
    let (body, sum) = bytes.split_at_checked(bytes.len().saturating_sub(8)).ok_or("the file is empty")?;
    if body.len() < MAGIC.len() + 8 || &body[..MAGIC.len()] != MAGIC {
        return Err("not a body-context cache file of this format".into());
    }
    let mut r = Reader { bytes: body, at: MAGIC.len() };
    if r.u64()? != key {
        return Err("made for another body, resolution or build".into());
    }
    let mut h = Hasher::new();
    h.bytes(body);
    if sum != h.0.to_le_bytes() {
        return Err("its checksum does not match (a damaged file)".into());
    }
    let res = r.count(template_res, "template samples per side")?;
    let head = r.f32s(4)?;
    let values = r.f32s(res.pow(3))?;
    let template = TemplateSdf { res, min: Vec3::new(head[0], head[1], head[2]), cell: head[3], values };
    let n = r.count((tet_res.max(1) + 1).pow(3), "grid vertices")?;
    let canonical = r.f32s(3 * n)?.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect();
    let values = r.f32s(n)?;
    let band_len = r.u64()? as usize;
    if band_len > n {
        return Err(format!("a band of {band_len} vertices in a grid of {n}"));
    }
    let band: Vec<u32> = r.words(band_len)?.map(u32::from_le_bytes).collect();
    if band.iter().any(|&i| i as usize >= n) {
        return Err("a band vertex outside the grid".into());
    }
    if r.at != body.len() {
        return Err(format!("{} bytes after the band", body.len() - r.at));
    }
    Ok((template, PosedGrid { canonical, template: values, band }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn same(a: &BodyContext, b: &BodyContext) {
        assert_eq!(a.template.res, b.template.res);
        assert_eq!(a.template.min, b.template.min);
        assert_eq!(a.template.cell.to_bits(), b.template.cell.to_bits());
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&a.template.values), bits(&b.template.values));
        assert_eq!(a.grid.vertices, b.grid.vertices);
        assert_eq!(a.grid.tets, b.grid.tets);
        assert_eq!(a.boundary, b.boundary);
        let (pa, pb) = (a.canonical_grid_made().expect("made"), b.canonical_grid_made().expect("made"));
        let points =
            |p: &PosedGrid| p.canonical.iter().flat_map(|v| v.to_array()).map(f32::to_bits).collect::<Vec<_>>();
        assert_eq!(points(pa), points(pb));
        assert_eq!(bits(&pa.template), bits(&pb.template));
        assert_eq!(pa.band, pb.band);
        assert!(!pa.band.is_empty());
    }

    #[test]
    fn the_hash_of_bytes_is_their_length_then_their_padded_words() {
        let words = |ws: &[u64]| {
            let mut h = Hasher::new();
            ws.iter().for_each(|&w| h.word(w));
            h.0
        };
        let hashed = |b: &[u8]| {
            let mut h = Hasher::new();
            h.bytes(b);
            h.0
        };
        let le = |b: &[u8; 8]| u64::from_le_bytes(*b);
        assert_eq!(hashed(b"abcdefghijklm"), words(&[13, le(b"abcdefgh"), le(b"ijklm\0\0\0")]));
        assert_eq!(hashed(b"abcdefgh"), words(&[8, le(b"abcdefgh"), 0]));
        assert_eq!(hashed(b""), words(&[0, 0]));
        assert_ne!(SOURCES, hashed(b""));
    }

    #[test]
    fn a_context_read_back_is_the_built_one_bit_for_bit_and_damaged_bytes_are_refused() {
        let body = BodyModel::default_body().expect("the embedded body");
        let built = build(body.clone(), 24, 12);
        let bytes = to_bytes(&built).expect("the bytes");
        let loaded = from_bytes(body.clone(), &bytes, 24, 12).expect("read back");
        same(&built, &loaded);
        // Another resolution is another file, and these bytes are not its.
        assert_ne!(file_name(&body, 24, 12), file_name(&body, 24, 10));
        assert!(from_bytes(body.clone(), &bytes, 24, 10).is_err());
        // One flipped bit in the values.
        let mut damaged = bytes.clone();
        let mid = damaged.len() / 2;
        damaged[mid] ^= 0x10;
        let why = from_bytes(body.clone(), &damaged, 24, 12).err().expect("refused");
        assert!(why.contains("checksum"), "{why}");
        // Cut short, and of another key.
        assert!(from_bytes(body.clone(), &bytes[..bytes.len() / 3], 24, 12).is_err());
        let mut other = bytes.clone();
        other[8] ^= 1;
        let why = from_bytes(body.clone(), &other, 24, 12).err().expect("refused");
        assert!(why.contains("another body"), "{why}");
        assert!(from_bytes(body, &[], 24, 12).is_err());
        // A context whose canonical grid is still to be made has no bytes yet.
        assert!(to_bytes(&BodyContext::with_resolution(BodyModel::default_body().expect("body"), 16, 8)).is_err());
    }
}
