//! Reading and writing NumPy `.npy` arrays and `.npz` archives (the format of the official
//! SMPL model files), without NumPy.
//!
//! Only what model files use is supported: little-endian `f4`/`f8`/`i4`/`i8`/`u4`/`u8`/`u1`/
//! `b1`, C or Fortran order, any rank. Values are converted to `f64` or `i64` on read.

use std::collections::BTreeMap;
use std::io::{Cursor, Read, Write};

/// Errors from npy/npz parsing. Every variant names the array (`key`) it concerns.
#[derive(Debug, thiserror::Error)]
pub enum NpzError {
    #[error("not a readable .npz (zip) archive: {0}")]
    Zip(String),
    #[error("array `{key}`: {msg}")]
    Array { key: String, msg: String },
    #[error("missing array `{0}`")]
    Missing(String),
}

fn arr_err(key: &str, msg: impl Into<String>) -> NpzError {
    NpzError::Array { key: key.to_string(), msg: msg.into() }
}

/// Element type of an array as stored.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DType {
    F32,
    F64,
    I32,
    I64,
    U32,
    U64,
    U8,
    Bool,
}

impl DType {
    fn parse(descr: &str) -> Option<(DType, usize)> {
        let d = descr.trim_start_matches(['<', '|', '=']);
        Some(match d {
            "f4" => (DType::F32, 4),
            "f8" => (DType::F64, 8),
            "i4" => (DType::I32, 4),
            "i8" => (DType::I64, 8),
            "u4" => (DType::U32, 4),
            "u8" => (DType::U64, 8),
            "u1" => (DType::U8, 1),
            "b1" => (DType::Bool, 1),
            _ => return None,
        })
    }
    fn descr(self) -> &'static str {
        match self {
            DType::F32 => "<f4",
            DType::F64 => "<f8",
            DType::I32 => "<i4",
            DType::I64 => "<i8",
            DType::U32 => "<u4",
            DType::U64 => "<u8",
            DType::U8 => "|u1",
            DType::Bool => "|b1",
        }
    }
}

/// A dense array in C (row-major) order.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: NpyData,
}

/// Array values, widened.
#[derive(Clone, Debug, PartialEq)]
pub enum NpyData {
    Float(Vec<f64>, DType),
    Int(Vec<i64>, DType),
}

impl NpyArray {
    pub fn f32(shape: Vec<usize>, data: Vec<f32>) -> Self {
        Self { shape, data: NpyData::Float(data.into_iter().map(f64::from).collect(), DType::F32) }
    }
    pub fn f64(shape: Vec<usize>, data: Vec<f64>) -> Self {
        Self { shape, data: NpyData::Float(data, DType::F64) }
    }
    pub fn i64(shape: Vec<usize>, data: Vec<i64>) -> Self {
        Self { shape, data: NpyData::Int(data, DType::I64) }
    }
    pub fn u32(shape: Vec<usize>, data: Vec<u32>) -> Self {
        Self { shape, data: NpyData::Int(data.into_iter().map(i64::from).collect(), DType::U32) }
    }
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Values as f64 (integers converted).
    pub fn to_f64(&self) -> Vec<f64> {
        match &self.data {
            NpyData::Float(v, _) => v.clone(),
            NpyData::Int(v, _) => v.iter().map(|&x| x as f64).collect(),
        }
    }
    /// Values as f32.
    pub fn to_f32(&self) -> Vec<f32> {
        match &self.data {
            NpyData::Float(v, _) => v.iter().map(|&x| x as f32).collect(),
            NpyData::Int(v, _) => v.iter().map(|&x| x as f32).collect(),
        }
    }
    /// Values as i64; floats must be integral.
    pub fn to_i64(&self, key: &str) -> Result<Vec<i64>, NpzError> {
        match &self.data {
            NpyData::Int(v, _) => Ok(v.clone()),
            NpyData::Float(v, _) => v
                .iter()
                .map(|&x| {
                    if x.fract() == 0.0 && x.is_finite() {
                        Ok(x as i64)
                    } else {
                        Err(arr_err(key, format!("expected integers, found {x}")))
                    }
                })
                .collect(),
        }
    }
    /// Whether every value is zero (without copying them).
    pub fn is_all_zero(&self) -> bool {
        match &self.data {
            NpyData::Float(v, _) => v.iter().all(|x| *x == 0.0),
            NpyData::Int(v, _) => v.iter().all(|x| *x == 0),
        }
    }
    pub fn dtype(&self) -> DType {
        match &self.data {
            NpyData::Float(_, d) | NpyData::Int(_, d) => *d,
        }
    }
}

/// Parse one `.npy` file.
pub fn read_npy(key: &str, bytes: &[u8]) -> Result<NpyArray, NpzError> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(arr_err(key, "not an .npy array (bad magic)"));
    }
    let major = bytes[6];
    let (hlen, hstart) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(arr_err(key, "truncated header"));
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(arr_err(key, format!("unsupported .npy version {v}"))),
    };
    let header = bytes.get(hstart..hstart + hlen).ok_or_else(|| arr_err(key, "truncated header"))?;
    let header = std::str::from_utf8(header).map_err(|_| arr_err(key, "header is not text"))?;
    let descr = header_value(header, "descr").ok_or_else(|| arr_err(key, "header lacks 'descr'"))?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    if descr.starts_with('>') {
        return Err(arr_err(key, format!("big-endian dtype {descr} is not supported")));
    }
    let (dtype, size) = DType::parse(descr).ok_or_else(|| arr_err(key, format!("unsupported dtype {descr}")))?;
    let fortran = header_value(header, "fortran_order").map(|v| v.trim() == "True").unwrap_or(false);
    let shape_txt = header_value(header, "shape").ok_or_else(|| arr_err(key, "header lacks 'shape'"))?;
    let shape: Vec<usize> = shape_txt
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.trim_end_matches('L').parse::<usize>())
        .collect::<Result<_, _>>()
        .map_err(|_| arr_err(key, format!("bad shape {shape_txt}")))?;
    // The declared shape is checked against the bytes present before anything is allocated
    // (a tiny file may claim a huge array; the product may overflow).
    let need = shape.iter().try_fold(size, |acc, d| acc.checked_mul(*d));
    let body = &bytes[hstart + hlen..];
    let Some(need) = need.filter(|n| *n <= body.len()) else {
        return Err(arr_err(
            key,
            format!("data truncated: shape {shape:?} needs more bytes than the file's {}", body.len()),
        ));
    };
    let n = need / size;
    let body = &body[..need];
    // An all-zero array (a body model's absent pose correctives: 33 MB of zeros) is allocated
    // zeroed, which the system maps lazily, instead of converted value by value.
    if body.iter().all(|&b| b == 0) {
        let data = match dtype {
            DType::F32 | DType::F64 => NpyData::Float(vec![0.0; n], dtype),
            _ => NpyData::Int(vec![0; n], dtype),
        };
        return Ok(NpyArray { shape, data });
    }
    // Little-endian values of `size` bytes each (`body` holds exactly `n` of them).
    fn values<const N: usize, T>(body: &[u8], f: impl Fn([u8; N]) -> T) -> Vec<T> {
        body.chunks_exact(N).map(|c| f(c.try_into().unwrap_or([0; N]))).collect()
    }
    let mut data = match dtype {
        DType::F32 => NpyData::Float(values(body, |b| f32::from_le_bytes(b) as f64), dtype),
        DType::F64 => NpyData::Float(values(body, f64::from_le_bytes), dtype),
        DType::I32 => NpyData::Int(values(body, |b| i32::from_le_bytes(b) as i64), dtype),
        DType::I64 => NpyData::Int(values(body, i64::from_le_bytes), dtype),
        DType::U32 => NpyData::Int(values(body, |b| u32::from_le_bytes(b) as i64), dtype),
        DType::U64 => NpyData::Int(values(body, |b| u64::from_le_bytes(b) as i64), dtype),
        DType::U8 | DType::Bool => NpyData::Int(body[..n].iter().map(|&b| b as i64).collect(), dtype),
    };
    if fortran && shape.len() > 1 {
        data = match data {
            NpyData::Float(v, d) => NpyData::Float(fortran_to_c(&v, &shape), d),
            NpyData::Int(v, d) => NpyData::Int(fortran_to_c(&v, &shape), d),
        };
    }
    Ok(NpyArray { shape, data })
}

fn fortran_to_c<T: Copy>(v: &[T], shape: &[usize]) -> Vec<T> {
    let n = v.len();
    let mut out = Vec::with_capacity(n);
    let rank = shape.len();
    let mut idx = vec![0usize; rank];
    for _ in 0..n {
        // idx is the C-order multi-index of the next output element.
        let mut off = 0;
        let mut stride = 1;
        for d in 0..rank {
            off += idx[d] * stride;
            stride *= shape[d];
        }
        out.push(v[off]);
        for d in (0..rank).rev() {
            idx[d] += 1;
            if idx[d] < shape[d] {
                break;
            }
            idx[d] = 0;
        }
    }
    out
}

/// Find `'key': value` in a Python dict literal header.
fn header_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let pat_a = format!("'{key}'");
    let pat_b = format!("\"{key}\"");
    let start =
        header.find(&pat_a).map(|p| p + pat_a.len()).or_else(|| header.find(&pat_b).map(|p| p + pat_b.len()))?;
    let rest = header[start..].trim_start().strip_prefix(':')?.trim_start();
    if rest.starts_with('(') {
        let end = rest.find(')')?;
        Some(&rest[..=end])
    } else {
        let end = rest.find([',', '}']).unwrap_or(rest.len());
        Some(rest[..end].trim())
    }
}

/// Serialise an array as `.npy` (version 1.0, C order, little endian).
pub fn write_npy(arr: &NpyArray) -> Vec<u8> {
    let dtype = arr.dtype();
    let shape = match arr.shape.len() {
        1 => format!("({},)", arr.shape[0]),
        _ => format!("({})", arr.shape.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '{}', 'fortran_order': False, 'shape': {}, }}", dtype.descr(), shape);
    let total = 10 + header.len() + 1;
    let pad = (64 - total % 64) % 64;
    header.push_str(&" ".repeat(pad));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + arr.len() * 8);
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    match &arr.data {
        NpyData::Float(v, DType::F32) => v.iter().for_each(|&x| out.extend_from_slice(&(x as f32).to_le_bytes())),
        NpyData::Float(v, _) => v.iter().for_each(|&x| out.extend_from_slice(&x.to_le_bytes())),
        NpyData::Int(v, DType::I32) => v.iter().for_each(|&x| out.extend_from_slice(&(x as i32).to_le_bytes())),
        NpyData::Int(v, DType::U32) => v.iter().for_each(|&x| out.extend_from_slice(&(x as u32).to_le_bytes())),
        NpyData::Int(v, DType::U64) => v.iter().for_each(|&x| out.extend_from_slice(&(x as u64).to_le_bytes())),
        NpyData::Int(v, DType::U8 | DType::Bool) => v.iter().for_each(|&x| out.push(x as u8)),
        NpyData::Int(v, _) => v.iter().for_each(|&x| out.extend_from_slice(&x.to_le_bytes())),
    }
    out
}

/// All arrays of an `.npz` archive, by key (file name without `.npy`).
pub fn read_npz(bytes: &[u8]) -> Result<BTreeMap<String, NpyArray>, NpzError> {
    read_npz_arrays(bytes, None)
}

/// Largest array an archive may hold, bytes uncompressed (a zip's sizes are claims: the
/// reader stops at this many bytes rather than trusting them).
pub const MAX_NPY_BYTES: u64 = 2 << 30;

/// Read only the arrays named in `keys` (others — strings, objects — are skipped unread);
/// `None` reads all.
pub fn read_npz_arrays(bytes: &[u8], keys: Option<&[&str]>) -> Result<BTreeMap<String, NpyArray>, NpzError> {
    let mut zip = zip::ZipArchive::new(Cursor::new(bytes)).map_err(|e| NpzError::Zip(e.to_string()))?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let file = zip.by_index(i).map_err(|e| NpzError::Zip(e.to_string()))?;
        let name = file.name().to_string();
        let key = name.strip_suffix(".npy").unwrap_or(&name).to_string();
        if keys.is_some_and(|k| !k.contains(&key.as_str())) {
            continue;
        }
        let claimed = file.size();
        let mut buf = Vec::with_capacity(claimed.min(64 << 20) as usize);
        file.take(MAX_NPY_BYTES + 1)
            .read_to_end(&mut buf)
            .map_err(|e| arr_err(&key, format!("cannot decompress: {e}")))?;
        if buf.len() as u64 > MAX_NPY_BYTES {
            return Err(arr_err(&key, format!("larger than {} GiB", MAX_NPY_BYTES >> 30)));
        }
        out.insert(key.clone(), read_npy(&key, &buf)?);
    }
    Ok(out)
}

/// Write arrays as a compressed `.npz` (like `numpy.savez_compressed`).
pub fn write_npz(arrays: &BTreeMap<String, NpyArray>) -> Result<Vec<u8>, NpzError> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .last_modified_time(zip::DateTime::default());
    for (key, arr) in arrays {
        zip.start_file(format!("{key}.npy"), opts).map_err(|e| NpzError::Zip(e.to_string()))?;
        zip.write_all(&write_npy(arr)).map_err(|e| NpzError::Zip(e.to_string()))?;
    }
    let cursor = zip.finish().map_err(|e| NpzError::Zip(e.to_string()))?;
    Ok(cursor.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_round_trip_all_dtypes() {
        let arrays = [
            NpyArray::f32(vec![2, 3], vec![1.0, -2.5, 3.25, 0.0, 1e-3, 7.0]),
            NpyArray::f64(vec![3], vec![1.0, 2.0, std::f64::consts::PI]),
            NpyArray::i64(vec![2, 2], vec![-1, 4294967295, 3, 0]),
            NpyArray::u32(vec![1, 3], vec![0, 1, 4000000000]),
            // All zeros (read without converting each value), and a negative zero (not all
            // zero bytes).
            NpyArray::f32(vec![2, 2], vec![0.0; 4]),
            NpyArray::f64(vec![3], vec![0.0; 3]),
            NpyArray::i64(vec![2], vec![0, 0]),
            NpyArray::f32(vec![2], vec![0.0, -0.0]),
        ];
        for a in arrays {
            let b = read_npy("x", &write_npy(&a)).expect("round trip");
            assert_eq!(a, b);
            assert_eq!(a.dtype(), b.dtype());
            assert_eq!(a.is_all_zero(), a.to_f64().iter().all(|x| *x == 0.0));
            assert_eq!(
                b.to_f64().iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                a.to_f64().iter().map(|x| x.to_bits()).collect::<Vec<_>>()
            );
        }
    }

    #[test]
    fn fortran_order_is_transposed() {
        // 2x3 matrix [[0,1,2],[3,4,5]] stored column-major: 0,3,1,4,2,5
        let mut bytes = write_npy(&NpyArray::i64(vec![2, 3], vec![0, 3, 1, 4, 2, 5]));
        let (from, to) = (b"'fortran_order': False", b"'fortran_order': True ");
        let pos = bytes.windows(from.len()).position(|w| w == from).expect("header field");
        bytes[pos..pos + to.len()].copy_from_slice(to);
        let a = read_npy("m", &bytes).expect("parse");
        assert_eq!(a.to_i64("m").expect("ints"), vec![0, 1, 2, 3, 4, 5]);
    }

    #[test]
    fn truncated_and_garbage_inputs_are_errors() {
        let good = write_npy(&NpyArray::f32(vec![4], vec![1.0; 4]));
        let err = read_npy("weights", &good[..good.len() - 3]).unwrap_err();
        assert!(err.to_string().contains("weights"), "{err}");
        assert!(read_npy("k", b"hello").is_err());
        assert!(read_npz(b"not a zip").is_err());
    }
}
