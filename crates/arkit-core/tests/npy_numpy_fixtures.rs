//! The NumPy reader on files numpy itself wrote (fixtures/numpy, made by the script
//! beside them), and our writer against numpy's bytes.

use arkit_core::{ArrayData, DType, NpyArray};
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    crate::support::workspace()
        .join("fixtures/numpy")
        .join(name)
}

#[test]
fn float_and_integer_arrays() {
    let a = arkit_core::read_npy(&fixture("f32_c_2x3.npy")).unwrap();
    assert_eq!(a.shape(), &[2, 3]);
    assert_eq!(
        a.data(),
        &ArrayData::F32((0..6).map(|i| i as f32 * 0.5 - 1.0).collect())
    );
    let a = arkit_core::read_npy(&fixture("f64_1d.npy")).unwrap();
    assert_eq!(
        a.data(),
        &ArrayData::F64((0..5).map(|i| i as f64 / 3.0).collect())
    );
    let a = arkit_core::read_npy(&fixture("i64_1d.npy")).unwrap();
    assert_eq!(
        a.to_i64_vec().unwrap(),
        (-3..4).map(|i| i * 1_000_000_007).collect::<Vec<i64>>()
    );
    let a = arkit_core::read_npy(&fixture("i32_2x2.npy")).unwrap();
    assert_eq!(a.data(), &ArrayData::I32(vec![i32::MIN, -1, 0, i32::MAX]));
    let a = arkit_core::read_npy(&fixture("u8_1d.npy")).unwrap();
    assert_eq!(a.data(), &ArrayData::U8(vec![0, 51, 102, 153, 204, 255]));
    let a = arkit_core::read_npy(&fixture("bool_1d.npy")).unwrap();
    assert_eq!(a.data(), &ArrayData::Bool(vec![true, false, true, true]));
    let a = arkit_core::read_npy(&fixture("f64_big_endian.npy")).unwrap();
    assert_eq!(a.data(), &ArrayData::F64(vec![0.25, 1.25, 2.25, 3.25]));
    let a = arkit_core::read_npy(&fixture("f64_scalar.npy")).unwrap();
    assert!(a.shape().is_empty());
    assert_eq!(a.to_f64_vec(), vec![2.5]);
}

#[test]
fn fortran_order_arrays_come_back_in_c_order() {
    // Like the release's triangles.npy: uint16, Fortran order.
    let a = arkit_core::read_npy(&fixture("u16_fortran_4x3.npy")).unwrap();
    assert_eq!(a.dtype(), DType::U16);
    assert_eq!(a.shape(), &[4, 3]);
    assert_eq!(a.data(), &ArrayData::U16((0..12).collect()));
    let a = arkit_core::read_npy(&fixture("f32_fortran_2x3x2.npy")).unwrap();
    assert_eq!(a.shape(), &[2, 3, 2]);
    assert_eq!(
        a.data(),
        &ArrayData::F32((0..12).map(|i| i as f32).collect())
    );
}

#[test]
fn unsupported_dtype_is_named() {
    let e = arkit_core::read_npy(&fixture("unicode_unsupported.npy"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("unicode_unsupported.npy") && e.contains("unsupported dtype '<U2'"),
        "{e}"
    );
}

#[test]
fn savez_and_savez_compressed_archives() {
    for name in ["savez_stored.npz", "savez_compressed.npz"] {
        let z = arkit_core::read_npz(&fixture(name)).unwrap();
        assert_eq!(z.keys().collect::<Vec<_>>(), vec!["verts", "R_t", "kpt"]);
        let verts = z.require_finite_f64("verts", &[5, 3]).unwrap();
        assert_eq!(
            verts,
            (0..15)
                .map(|i| (i as f32 / 100.0) as f64)
                .collect::<Vec<_>>()
        );
        let rt = z.require_finite_f64("R_t", &[4, 4]).unwrap();
        assert_eq!(&rt[12..16], &[0.01, -0.02, -0.5, 1.0]);
        assert_eq!(
            z.require("kpt").unwrap().to_i64_vec().unwrap(),
            vec![0, 1, 2]
        );
    }
}

#[test]
fn our_npy_bytes_equal_numpys() {
    let cases = [
        (
            "f32_c_2x3.npy",
            NpyArray::from_f32(vec![2, 3], (0..6).map(|i| i as f32 * 0.5 - 1.0).collect()).unwrap(),
        ),
        (
            "f64_1d.npy",
            NpyArray::from_f64(vec![5], (0..5).map(|i| i as f64 / 3.0).collect()).unwrap(),
        ),
        (
            "i64_1d.npy",
            NpyArray::from_i64(vec![7], (-3..4).map(|i| i * 1_000_000_007).collect()).unwrap(),
        ),
        (
            "f64_scalar.npy",
            NpyArray::from_f64(vec![], vec![2.5]).unwrap(),
        ),
        (
            "bool_1d.npy",
            NpyArray::new(vec![4], ArrayData::Bool(vec![true, false, true, true])).unwrap(),
        ),
        (
            "u8_1d.npy",
            NpyArray::new(vec![6], ArrayData::U8(vec![0, 51, 102, 153, 204, 255])).unwrap(),
        ),
    ];
    for (name, array) in cases {
        let mut ours = Vec::new();
        arkit_core::write_npy(&mut ours, &array).unwrap();
        assert_eq!(ours, std::fs::read(fixture(name)).unwrap(), "{name}");
    }
}
