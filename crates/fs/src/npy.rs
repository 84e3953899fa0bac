//! NumPy `.npy` arrays of `f64` (little-endian, C order): the array format of datasets, so
//! `numpy.load` reads them directly. Writes are atomic; reads check every header field and
//! the data length and name the file in errors.

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
pub struct Array {
    /// The shape (C order: the last index varies fastest).
    pub shape: Vec<usize>,
    /// The values.
    pub data: Vec<f64>,
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
    let descr = field("descr")?;
    if !(descr.starts_with("'<f8'") || descr.starts_with("'float64'")) {
        let shown: String = descr.chars().take(12).collect();
        return Err(format!(
            "dtype {shown}... is not little-endian float64 ('<f8')"
        ));
    }
    if !field("fortran_order")?.starts_with("False") {
        return Err("Fortran-ordered arrays are not supported (save with C order)".into());
    }
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
        .try_fold(8usize, |a, &b| a.checked_mul(b))
        .ok_or("shape overflows")?;
    let body = &bytes[end..];
    if body.len() != needed {
        return Err(format!(
            "shape {shape:?} needs {needed} bytes of data, the file has {}",
            body.len()
        ));
    }
    let data = body
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().expect("chunks of 8")))
        .collect();
    Ok(Array { shape, data })
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
        let mut ints = bytes.clone();
        let at = ints.windows(3).position(|w| w == b"<f8").unwrap();
        ints[at + 1] = b'i';
        assert!(parse(&ints).unwrap_err().reason.contains("float64"));
        assert!(parse(b"hello").is_err());
        let e = read(&dir.path().join("missing.npy"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing.npy"), "{e}");
    }
}
