//! `mesh_codec`: a record's mesh (`V x 3` float32, as `_info.npz` has it) in its stored
//! bytes and back, bit for bit. Uses [`super::zstd_frame`].

use super::zstd_frame::zstd_frame;
use arkit_core::{Error, Result};
use nalgebra::Point3;

/// The bytes a record stores for `verts`: their float32 bits, coordinate by coordinate
/// (every x, then every y, then every z) and byte plane by byte plane (the lowest byte
/// of each value, then the next, ...), compressed by zstd (one frame, level 19). The
/// planes put the values' sign and exponent bytes, which vary little from one vertex to
/// the next, side by side, where zstd finds them; the bits are kept, NaN, -0.0 and
/// denormals included. (Deflate at its best level gives 1-2% more bytes and inflates
/// in about five times zstd's time.)
pub fn encode_mesh(verts: &[Point3<f32>]) -> Vec<u8> {
    let n = verts.len();
    let mut planes = vec![0u8; 12 * n];
    for (i, p) in verts.iter().enumerate() {
        for (c, v) in [p.x, p.y, p.z].into_iter().enumerate() {
            for (k, b) in v.to_bits().to_le_bytes().into_iter().enumerate() {
                planes[(4 * c + k) * n + i] = b;
            }
        }
    }
    zstd::bulk::compress(&planes, MESH_LEVEL).expect("zstd compresses any bytes into a Vec")
}

/// zstd's level for meshes: its slowest, written once; its decoding is as fast as at
/// any other level.
const MESH_LEVEL: i32 = 19;

/// The most bytes a stored mesh of `vertex_count` vertices can take: zstd's bound for
/// its `12 V` bytes (stored blocks and the frame's header).
pub(super) fn max_mesh_bytes(vertex_count: usize) -> usize {
    zstd::zstd_safe::compress_bound(12 * vertex_count)
}

/// The `vertex_count` vertices that `bytes` ([`encode_mesh`]) hold. Bounded: the frame
/// is decoded into a buffer of exactly `12 V` bytes, and one that would give more or
/// fewer, or is not a zstd frame, is refused.
pub fn decode_mesh(bytes: &[u8], vertex_count: usize) -> Result<Vec<Point3<f32>>> {
    let n = vertex_count;
    let want = 12 * n;
    let bad = |why: String| Error::invalid("crop store", format!("its mesh: {why}"));
    let planes = zstd_frame(bytes, want).map_err(|e| {
        bad(format!(
            "not a zstd frame of at most the {want} bytes of {n} vertices ({e})"
        ))
    })?;
    if planes.len() != want {
        return Err(bad(format!(
            "{} bytes, expected the {want} of {n} vertices",
            planes.len()
        )));
    }
    let value = |i: usize, c: usize| {
        let b = |k: usize| planes[(4 * c + k) * n + i];
        f32::from_bits(u32::from_le_bytes([b(0), b(1), b(2), b(3)]))
    };
    Ok((0..n)
        .map(|i| Point3::new(value(i, 0), value(i, 1), value(i, 2)))
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The two vertices of the store tests' crop.
    fn two() -> Vec<Point3<f32>> {
        vec![Point3::new(0.1, -0.2, 0.3), Point3::new(1.0, 2.0, 3.0)]
    }

    /// The bits of `verts`, for comparisons that tell NaNs and -0.0 apart.
    fn bits(verts: &[Point3<f32>]) -> Vec<u32> {
        verts
            .iter()
            .flat_map(|p| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()])
            .collect()
    }

    #[test]
    fn a_mesh_round_trips_bit_for_bit_nans_zeros_and_denormals_included() {
        let odd = [
            f32::NAN,
            f32::from_bits(0x7fc0_1234),
            f32::from_bits(0xffbf_ffff),
            -0.0,
            0.0,
            f32::from_bits(1),
            -f32::from_bits(0x007f_ffff),
            f32::MIN_POSITIVE,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::MAX,
            -1.5e-3,
        ];
        // A face-like mesh (smooth, centimetres in metres) with the odd values in it.
        let mut verts: Vec<Point3<f32>> = (0..1220)
            .map(|i| {
                let t = i as f32 * 0.013;
                Point3::new(
                    0.08 * t.sin(),
                    0.09 * (0.7 * t).cos(),
                    0.02 + 0.03 * t.cos(),
                )
            })
            .collect();
        for (i, v) in odd.iter().enumerate() {
            verts[37 * i].x = *v;
            verts[37 * i + 5].y = *v;
            verts[37 * i + 11].z = -*v;
        }
        let stored = encode_mesh(&verts);
        assert!(stored.len() < 12 * verts.len(), "{} bytes", stored.len());
        assert!(stored.len() <= max_mesh_bytes(verts.len()));
        assert_eq!(
            bits(&decode_mesh(&stored, verts.len()).unwrap()),
            bits(&verts)
        );
        // Every value alone, and no vertices at all.
        let each: Vec<Point3<f32>> = odd.iter().map(|&v| Point3::new(v, -v, v)).collect();
        let back = decode_mesh(&encode_mesh(&each), each.len()).unwrap();
        assert_eq!(bits(&back), bits(&each));
        assert!(decode_mesh(&encode_mesh(&[]), 0).unwrap().is_empty());
        // Random bits (nothing to compress): still within the bound, still exact.
        let mut x = 0x9e37_79b9_u32;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            f32::from_bits(x)
        };
        let noise: Vec<Point3<f32>> = (0..1220)
            .map(|_| Point3::new(next(), next(), next()))
            .collect();
        let stored = encode_mesh(&noise);
        assert!(
            stored.len() <= max_mesh_bytes(noise.len()),
            "{}",
            stored.len()
        );
        assert_eq!(
            bits(&decode_mesh(&stored, noise.len()).unwrap()),
            bits(&noise)
        );
    }

    #[test]
    fn a_mesh_stream_cut_short_grown_or_of_another_size_is_refused() {
        let verts = two();
        let stored = encode_mesh(&verts);
        // Cut: every shorter frame refused.
        for cut in 0..stored.len() {
            assert!(decode_mesh(&stored[..cut], 2).is_err(), "cut to {cut}");
        }
        // Bytes after the frame's end.
        let mut more = stored.clone();
        more.push(0);
        let e = decode_mesh(&more, 2).unwrap_err().to_string();
        assert!(e.contains("its mesh: not a zstd frame"), "{e}");
        // The frame of a larger mesh, read as two vertices: it gives more than 24 bytes.
        let three = [verts[0], verts[1], verts[0]];
        let e = decode_mesh(&encode_mesh(&three), 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("at most the 24 bytes of 2 vertices"), "{e}");
        // The frame of a smaller mesh: it gives fewer.
        let e = decode_mesh(&encode_mesh(&verts[..1]), 2)
            .unwrap_err()
            .to_string();
        assert!(e.contains("12 bytes, expected the 24"), "{e}");
        // Not zstd at all.
        assert!(decode_mesh(&[0xff; 40], 2).is_err());
    }
}
