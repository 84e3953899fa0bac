//! `.npy` files written by numpy itself (`tests/data`, made with numpy 2 by `np.save`):
//! integer, big-endian and Fortran-ordered arrays read as the same C-order values.

use std::path::Path;

use deform_fs::npy;

fn read(name: &str) -> npy::Array {
    npy::read(
        &Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data")
            .join(name),
    )
    .unwrap()
}

#[test]
fn numpy_integer_big_endian_and_fortran_arrays_read_as_c_order_values() {
    // a = np.arange(24).reshape(2, 3, 4) - 5, saved in several dtypes and orders.
    let a: Vec<f64> = (0..24).map(|i| i as f64 - 5.0).collect();
    for (name, want) in [
        ("i8_c.npy", a.clone()),
        ("i4_fortran.npy", a.clone()),
        ("i1.npy", a.clone()),
        ("u2_big.npy", a.iter().map(|v| v.max(0.0)).collect()),
        ("f4_big_fortran.npy", a.iter().map(|v| v * 0.5).collect()),
        ("f8_big.npy", a.iter().map(|v| v * 0.25).collect()),
    ] {
        let got = read(name);
        assert_eq!(got.shape, [2, 3, 4], "{name}");
        assert_eq!(got.data, want, "{name}");
    }
    // Indices: non-negative integers only, the offending value named.
    assert_eq!(
        read("u2_big.npy").indices().unwrap()[..7],
        [0, 0, 0, 0, 0, 0, 1]
    );
    let e = read("i8_c.npy").indices().unwrap_err();
    assert!(e.contains("value 0 (-5)"), "{e}");
}

#[test]
fn unsupported_dtypes_and_inexact_integers_are_refused() {
    let bytes = |descr: &str, data: &[u8]| {
        let header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': (1,), }}\n");
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((header.len() as u16).to_le_bytes());
        b.extend(header.as_bytes());
        b.extend(data);
        b
    };
    let e = npy::parse(&bytes("<c16", &[0; 16])).unwrap_err();
    assert!(e.reason.contains("<c16"), "{e}");
    assert!(npy::parse(&bytes("<U3", &[0; 12])).is_err());
    // 2^53 + 1 cannot be a float64.
    let big = ((1u64 << 53) + 1).to_le_bytes();
    let e = npy::parse(&bytes("<u8", &big)).unwrap_err();
    assert!(e.reason.contains("2^53"), "{e}");
    let exact = (1u64 << 53).to_le_bytes();
    assert_eq!(
        npy::parse(&bytes("<u8", &exact)).unwrap().data,
        [(1u64 << 53) as f64]
    );
}
