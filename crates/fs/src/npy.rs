//! NumPy `.npy` arrays: the array format of datasets, so `numpy.load` reads them directly.
//! Writes are `f64` (little-endian, C order) and atomic. Reads take what numpy users have:
//! float32/64 and signed or unsigned 8- to 64-bit integers (vertex ids and tets are integer
//! arrays), either byte order, C or Fortran order, as `f64` values in C order (an integer
//! beyond 2^53, which `f64` cannot hold exactly, is refused); they check every header field
//! and the data length and name the file in errors.

use std::path::{Path, PathBuf};

use crate::write_atomic;
use thiserror::Error;

/// Why an `.npy` file could not be read or written.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum NpyError {
    /// The file could not be opened, read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        error: std::io::Error,
    },
    /// The header or data do not describe what deform reads.
    #[error("{path}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// An `f64` array with its shape.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct Array {
    /// The shape (C order: the last index varies fastest).
    pub shape: Vec<usize>,
    /// The values.
    pub data: Vec<f64>,
    /// numpy's name of the type the values were stored as (`float32`, `int64`, ...): what
    /// their precision was before they became `f64` ([`Array::rounding`]).
    pub dtype: String,
}

/// Writes `data` with `shape` as a version 1.0 `.npy` file.
///
/// # Errors
/// [`NpyError`] naming the file; a shape that does not match the data is a `Format` error.
pub fn write(path: &Path, shape: &[usize], data: &[f64]) -> Result<(), NpyError> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(NpyError::Format {
            path: path.to_owned(),
            reason: format!("shape {shape:?} does not hold {} values", data.len()),
        });
    }
    let dims: Vec<String> = shape.iter().map(usize::to_string).collect();
    let shape_text = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {shape_text}, }}");
    // Magic (6) + version (2) + length (2) + header + '\n' is a multiple of 64.
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    write_atomic(path, |w| {
        w.write_all(b"\x93NUMPY\x01\x00")?;
        w.write_all(&(header.len() as u16).to_le_bytes())?;
        w.write_all(header.as_bytes())?;
        let mut buf = Vec::with_capacity(8 * data.len());
        for v in data {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        w.write_all(&buf)
    })
    .map_err(|e| NpyError::Io {
        path: path.to_owned(),
        error: std::io::Error::other(e.to_string()),
    })
}

/// Reads an `f64` `.npy` file (versions 1.0 to 3.0, little-endian, C order).
///
/// # Errors
/// [`NpyError`] naming the file and what is wrong.
pub fn read(path: &Path) -> Result<Array, NpyError> {
    let bytes = std::fs::read(path).map_err(|error| NpyError::Io {
        path: path.to_owned(),
        error,
    })?;
    parse(&bytes).map_err(|e| NpyError::Format {
        path: path.to_owned(),
        reason: e.reason,
    })
}

/// Bytes that are not an `.npy` array deform reads: what is wrong with them.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("{reason}")]
pub struct FormatError {
    /// What is wrong (the header field, the size, the dtype).
    pub reason: String,
}

/// Parses the bytes of an `.npy` file.
///
/// # Errors
/// [`FormatError`] saying what is wrong.
pub fn parse(bytes: &[u8]) -> Result<Array, FormatError> {
    parse_bytes(bytes).map_err(|reason| FormatError { reason })
}

fn parse_bytes(bytes: &[u8]) -> Result<Array, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not an .npy file (bad magic)".into());
    }
    let (header_len, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err("truncated header".into());
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(format!("unsupported .npy version {v}")),
    };
    let end = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or("truncated header")?;
    let header = std::str::from_utf8(&bytes[start..end]).map_err(|_| "header is not text")?;
    let field = |key: &str| -> Result<&str, String> {
        let at = header
            .find(&format!("'{key}'"))
            .ok_or(format!("header has no '{key}'"))?;
        let rest = header[at + key.len() + 2..].trim_start();
        let rest = rest
            .strip_prefix(':')
            .ok_or(format!("'{key}' has no value"))?
            .trim_start();
        Ok(rest)
    };
    let dtype = Dtype::parse(field("descr")?)?;
    let fortran = match field("fortran_order")? {
        f if f.starts_with("False") => false,
        f if f.starts_with("True") => true,
        _ => return Err("'fortran_order' is neither True nor False".into()),
    };
    let shape_text = field("shape")?;
    let close = shape_text.find(')').ok_or("shape is not a tuple")?;
    let inner = shape_text.strip_prefix('(').ok_or("shape is not a tuple")?;
    let shape = inner[..close - 1]
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("bad shape entry '{s}'"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    // Counted in bytes, so that a hostile shape overflows here rather than below.
    let needed = shape
        .iter()
        .try_fold(dtype.size, |a, &b| a.checked_mul(b))
        .ok_or("shape overflows")?;
    let body = &bytes[end..];
    if body.len() != needed {
        return Err(format!(
            "shape {shape:?} needs {needed} bytes of data, the file has {}",
            body.len()
        ));
    }
    let values = body
        .chunks_exact(dtype.size)
        .map(|c| dtype.decode(c))
        .collect::<Result<Vec<f64>, String>>()?;
    let data = if fortran && shape.len() > 1 {
        c_order(&shape, &values)
    } else {
        values
    };
    Ok(Array {
        shape,
        data,
        dtype: dtype.name(),
    })
}

/// The element type of an `.npy` array deform reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Dtype {
    kind: char,
    size: usize,
    big_endian: bool,
}

impl Dtype {
    /// From the header's `descr` value (`'<f8'`, `'>i4'`, `'|u1'`, ...).
    fn parse(descr: &str) -> Result<Self, String> {
        let shown: String = descr.chars().take(12).collect();
        let unsupported =
            || format!("dtype {shown}... is not a float32/64 or 8- to 64-bit integer array");
        let text = descr
            .strip_prefix('\'')
            .and_then(|d| d.split('\'').next())
            .ok_or_else(unsupported)?;
        let mut chars = text.chars();
        let order = chars.next().ok_or_else(unsupported)?;
        let kind = chars.next().ok_or_else(unsupported)?;
        let size: usize = chars.as_str().parse().map_err(|_| unsupported())?;
        let big_endian = match order {
            '>' => true,
            '<' | '|' => false,
            '=' => cfg!(target_endian = "big"),
            _ => return Err(unsupported()),
        };
        match (kind, size) {
            ('f', 4 | 8) | ('i' | 'u', 1 | 2 | 4 | 8) => Ok(Self {
                kind,
                size,
                big_endian,
            }),
            _ => Err(unsupported()),
        }
    }

    /// numpy's name: `float32`, `int16`, `uint8`, ...
    fn name(self) -> String {
        let kind = match self.kind {
            'f' => "float",
            'i' => "int",
            _ => "uint",
        };
        format!("{kind}{}", 8 * self.size)
    }

    /// One value.
    fn decode(self, c: &[u8]) -> Result<f64, String> {
        let mut b = [0u8; 8];
        if self.big_endian {
            // Right-aligned big-endian bytes, reversed: little-endian in the low bytes.
            for (i, &x) in c.iter().rev().enumerate() {
                b[i] = x;
            }
        } else {
            b[..self.size].copy_from_slice(c);
        }
        let exact = |v: f64, i: i128| {
            if i.unsigned_abs() <= 1 << 53 {
                Ok(v)
            } else {
                Err(format!(
                    "integer {i} is beyond 2^53: not exact as a float64"
                ))
            }
        };
        let bits = u64::from_le_bytes(b);
        Ok(match (self.kind, self.size) {
            ('f', 8) => f64::from_bits(bits),
            ('f', _) => f32::from_bits(bits as u32) as f64,
            ('u', _) => exact(bits as f64, bits as i128)?,
            // Sign-extend from the value's width.
            (_, size) => {
                let shift = 64 - 8 * size as u32;
                let i = ((bits << shift) as i64) >> shift;
                exact(i as f64, i as i128)?
            }
        })
    }
}

/// Fortran-ordered `values` of `shape` (the first index varies fastest) in C order.
fn c_order(shape: &[usize], values: &[f64]) -> Vec<f64> {
    let mut strides = vec![1usize; shape.len()];
    for d in 1..shape.len() {
        strides[d] = strides[d - 1] * shape[d - 1];
    }
    let mut index = vec![0usize; shape.len()];
    let mut out = Vec::with_capacity(values.len());
    for _ in 0..values.len() {
        out.push(
            values[index
                .iter()
                .zip(&strides)
                .map(|(i, s)| i * s)
                .sum::<usize>()],
        );
        // The next C-order multi-index: the last index fastest.
        for d in (0..shape.len()).rev() {
            index[d] += 1;
            if index[d] < shape[d] {
                break;
            }
            index[d] = 0;
        }
    }
    out
}

/// The relative rounding of values stored as numpy's `dtype` ([`Array::rounding`]).
pub fn rounding_of(dtype: &str) -> f64 {
    match dtype {
        "float64" => f64::EPSILON,
        d if d.starts_with("float") => f32::EPSILON as f64,
        _ => 0.0,
    }
}

/// An empty float64 array (shape `[0]`).
impl Default for Array {
    fn default() -> Self {
        Self::new(vec![0], Vec::new())
    }
}

impl Array {
    /// The same values, stored before as numpy's `dtype` (`float32`, `int64`, ...).
    #[must_use]
    pub fn with_dtype(mut self, dtype: impl Into<String>) -> Self {
        self.dtype = dtype.into();
        self
    }

    /// Float64 values of `shape`.
    ///
    /// # Panics
    /// When `shape` does not hold `data`.
    #[track_caller]
    pub fn new(shape: Vec<usize>, data: Vec<f64>) -> Self {
        assert_eq!(
            shape.iter().product::<usize>(),
            data.len(),
            "shape and data"
        );
        Self {
            shape,
            data,
            dtype: "float64".into(),
        }
    }

    /// The relative rounding of the values as they were stored: float32's machine epsilon
    /// (1.2e-7) for `float32` (and `float16`, which deform does not read), float64's for
    /// floats of 64 bits, 0 for integers (exact).
    pub fn rounding(&self) -> f64 {
        rounding_of(&self.dtype)
    }

    /// The values as indices (vertex ids, tet corners): each must be a non-negative integer.
    ///
    /// # Errors
    /// The first value that is not, with its position.
    pub fn indices(&self) -> Result<Vec<usize>, String> {
        self.data
            .iter()
            .enumerate()
            .map(|(k, &v)| {
                if v >= 0.0 && v.fract() == 0.0 && v <= (1u64 << 53) as f64 {
                    Ok(v as usize)
                } else {
                    Err(format!(
                        "value {k} ({v}) is not a non-negative integer index"
                    ))
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.npy");
        let data: Vec<f64> = (0..24).map(|i| i as f64 * 0.5 - 3.0).collect();
        write(&path, &[2, 4, 3], &data).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!((bytes.len() - 24 * 8) % 64, 0, "header aligned to 64 bytes");
        let a = read(&path).unwrap();
        assert_eq!(a.shape, vec![2, 4, 3]);
        assert_eq!(a.data, data);
        write(&path, &[5], &data[..5]).unwrap();
        assert_eq!(read(&path).unwrap().shape, vec![5]);
        assert!(write(&path, &[3, 3], &data).is_err());
        // Found by the fuzzer: a shape whose element count fits in usize but whose byte
        // count does not (was an overflow panic).
        let header = "{'descr': '<f8', 'fortran_order': False, 'shape': (311,311,11,3111,8,, 33111,311,3, 3), }";
        let mut hostile = b"\x93NUMPY\x01\x00".to_vec();
        hostile.extend((header.len() as u16 + 1).to_le_bytes());
        hostile.extend(header.as_bytes());
        hostile.push(b'\n');
        assert!(parse(&hostile).is_err());
        // Truncated data, wrong dtype, garbage.
        let mut cut = bytes.clone();
        cut.truncate(bytes.len() - 8);
        assert!(parse(&cut).unwrap_err().reason.contains("bytes of data"));
        let mut complex = bytes.clone();
        let at = complex.windows(3).position(|w| w == b"<f8").unwrap();
        complex[at + 1] = b'c';
        assert!(parse(&complex).unwrap_err().reason.contains("float32/64"));
        assert!(parse(b"hello").is_err());
        let e = read(&dir.path().join("missing.npy"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.npy"), "{e}");
    }
}
