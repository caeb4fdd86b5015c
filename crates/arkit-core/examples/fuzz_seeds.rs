//! Writes the seed corpus of the fuzz targets (`fuzz/corpus/<target>/`) with this
//! crate's own writers: `cargo run --release -p arkit-core --example fuzz_seeds -- fuzz/corpus`.
//! Deterministic: running it again writes the same bytes.

use arkit_core::InfoAnnotation;
use arkit_core::{ArrayData, NpyArray, NpzCompression};
use nalgebra::Point3;
use std::path::Path;

fn npy_bytes(a: &NpyArray) -> Vec<u8> {
    let mut b = Vec::new();
    arkit_core::write_npy(&mut b, a).expect("write");
    b
}

fn npz_bytes(members: &[(&str, &NpyArray)], c: NpzCompression) -> Vec<u8> {
    let mut cur = std::io::Cursor::new(Vec::new());
    arkit_core::write_npz(&mut cur, members, c).expect("write");
    cur.into_inner()
}

fn put(dir: &Path, target: &str, name: &str, bytes: &[u8]) {
    let d = dir.join(target);
    std::fs::create_dir_all(&d).expect("mkdir");
    std::fs::write(d.join(name), bytes).expect("write");
}

fn main() {
    let dir = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "fuzz/corpus".into());
    let dir = Path::new(&dir);
    let arrays = [
        NpyArray::from_f32(vec![4, 3], (0..12).map(|i| i as f32 * 0.5).collect()),
        NpyArray::from_f64(vec![], vec![std::f64::consts::PI]),
        NpyArray::new(vec![2, 2], ArrayData::U16(vec![1, 2, 3, 65535])),
        NpyArray::new(vec![3], ArrayData::Bool(vec![true, false, true])),
        NpyArray::new(vec![2, 1, 2], ArrayData::I64(vec![-1, 2, -3, 4])),
        NpyArray::new(vec![0, 5], ArrayData::U8(vec![])),
    ];
    let arrays: Vec<NpyArray> = arrays.into_iter().map(|a| a.expect("shape")).collect();
    for (i, a) in arrays.iter().enumerate() {
        put(dir, "npy", &format!("own_{i}.npy"), &npy_bytes(a));
    }
    // Hand-made headers: Fortran order, big-endian, version 2.0 and 3.0.
    let hand = |version: u8, header: &str, data: &[u8]| {
        let mut b = vec![0x93, b'N', b'U', b'M', b'P', b'Y', version, 0];
        let h = format!("{header}\n");
        if version == 1 {
            b.extend((h.len() as u16).to_le_bytes());
        } else {
            b.extend((h.len() as u32).to_le_bytes());
        }
        b.extend(h.as_bytes());
        b.extend(data);
        b
    };
    put(
        dir,
        "npy",
        "fortran.npy",
        &hand(
            1,
            "{'descr': '<u2', 'fortran_order': True, 'shape': (2, 3), }",
            &[0, 0, 3, 0, 1, 0, 4, 0, 2, 0, 5, 0],
        ),
    );
    put(
        dir,
        "npy",
        "big_endian.npy",
        &hand(
            1,
            "{'descr': '>i4', 'fortran_order': False, 'shape': (2,), }",
            &[0, 0, 0, 1, 255, 255, 255, 255],
        ),
    );
    put(
        dir,
        "npy",
        "v2.npy",
        &hand(
            2,
            "{\"descr\": \"<f8\", \"fortran_order\": False, \"shape\": (1,)}",
            &1.5f64.to_le_bytes(),
        ),
    );
    put(
        dir,
        "npy",
        "v3.npy",
        &hand(
            3,
            "{'descr': '|b1', 'fortran_order': False, 'shape': (2L,), }",
            &[1, 0],
        ),
    );

    let members: Vec<(String, &NpyArray)> = arrays
        .iter()
        .enumerate()
        .map(|(i, a)| (format!("a{i}"), a))
        .collect();
    let refs: Vec<(&str, &NpyArray)> = members.iter().map(|(k, a)| (k.as_str(), *a)).collect();
    put(
        dir,
        "npz",
        "stored.npz",
        &npz_bytes(&refs, NpzCompression::Stored),
    );
    put(
        dir,
        "npz",
        "deflated.npz",
        &npz_bytes(&refs, NpzCompression::Deflated),
    );
    put(
        dir,
        "npz",
        "one.npz",
        &npz_bytes(&refs[..1], NpzCompression::Deflated),
    );

    // `_info.npz`: a face at 0.5 m, with and without the optional keys.
    let verts: Vec<Point3<f32>> = (0..1220)
        .map(|i| Point3::new((i % 40) as f32 * 0.002, (i / 40) as f32 * 0.003, 0.01))
        .collect();
    let mut rt = [0.0; 16];
    for k in 0..4 {
        rt[k * 5] = 1.0;
    }
    rt[14] = -0.5;
    let info = InfoAnnotation {
        verts,
        rt,
        verts_gt: None,
        face_anchor_transform: None,
        camera_transform: None,
        projection_matrix: None,
        euler_angles_pyr: Some([0.0, 0.0, 0.0]),
        translation: Some([0.0, 0.0, -0.5]),
        points2d: None,
    };
    put(
        dir,
        "info_npz",
        "deflated_info.npz",
        &info.to_npz_bytes(NpzCompression::Deflated).expect("npz"),
    );
    put(
        dir,
        "info_npz",
        "stored_info.npz",
        &info.to_npz_bytes(NpzCompression::Stored).expect("npz"),
    );
    let mut bad = info.clone();
    bad.rt[14] = 0.5; // behind the camera
    put(
        dir,
        "info_npz",
        "behind_info.npz",
        &bad.to_npz_bytes(NpzCompression::Deflated).expect("npz"),
    );

    put(dir, "list_csv", "plain.csv", b"subject_id,facial_action,img_id\n225579,09_LeftToRight_Frown,1616212233525\n000123,01_Neutral,0001616\n");
    put(dir, "list_csv", "pandas.csv", b",subject_id,facial_action,img_id,extra\r\n0,000123,01_Neutral,0001616,x\r\n1,\"42\",\"a,b\",7,\"q\"\"q\"\r\n");
    put(
        dir,
        "list_csv",
        "bom.csv",
        "\u{feff}subject_id,facial_action,img_id\n1,a,2\n\n".as_bytes(),
    );
    put(
        dir,
        "list_csv",
        "bad_name.csv",
        b"subject_id,facial_action,img_id\n1,..,2\n",
    );

    put(
        dir,
        "predictions_csv",
        "poses.csv",
        b"subject_id,facial_action,img_id,R_t\n1,a,2,1 0 0 0 0 1 0 0 0 0 1 0 0 0 -0.5 1\n1,a,3,\n",
    );
    put(
        dir,
        "predictions_csv",
        "verts.csv",
        b"img_id,R_t,verts,subject_id,facial_action\n7,,0.5 -1e-3 2,s,a\n",
    );
    put(
        dir,
        "predictions_csv",
        "short.csv",
        b"subject_id,facial_action,img_id,R_t\n1,a,2,1 0 0\n",
    );

    // targets_blobs: [mask pixels u32][uv side u16][split u16][blob...].
    let blobs = |len: u32, uv: u16, split: u16, rest: &[u8]| {
        let mut b = len.to_le_bytes().to_vec();
        b.extend(uv.to_le_bytes());
        b.extend(split.to_le_bytes());
        b.extend(rest);
        b
    };
    let mask: Vec<bool> = (0..64).map(|i| (i / 3) % 2 == 1).collect();
    let runs = arkit_core::pack_u32_le(&arkit_core::rle_encode(&mask));
    put(
        dir,
        "targets_blobs",
        "mask.bin",
        &blobs(64, 0, runs.len() as u16, &runs),
    );
    let bits: Vec<u16> = (0..48u32).map(|i| (15360 + i * 7) as u16).collect();
    let uv = arkit_core::encode_uv_map(&bits, 4);
    put(dir, "targets_blobs", "uv4.bin", &blobs(0, 4, 0, &uv));
    let (v, w) =
        arkit_core::encode_correspondences(&[[1, 2, 3], [4, 5, 1219]], &[[65535, 0], [3, 4]]);
    let mut both = v.clone();
    both.extend(&w);
    put(
        dir,
        "targets_blobs",
        "corr.bin",
        &blobs(3, 0, v.len() as u16, &both),
    );
    put(
        dir,
        "targets_blobs",
        "claims.bin",
        &blobs(
            u32::MAX,
            65535,
            12,
            &[0, 0, 0, 128, 0, 0, 0, 128, 0, 0, 0, 128],
        ),
    );
}
