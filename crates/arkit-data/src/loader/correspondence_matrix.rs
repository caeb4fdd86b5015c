//! `correspondence_matrix`: the dense `n_pts x V` matrix the official loader returns as
//! `corr_mat`: row `r` holds point `r`'s three barycentric weights at its triangle's
//! three vertex columns and zeros elsewhere (`arkit_dataset.py` assigns the three
//! columns one after another, so where a triangle repeats a vertex the last weight
//! stays).
//!
//! The matrix is mostly zeros (3 of 1,220 values a row) and large (5 MB a sample at
//! 1,024 points), so writing it is the cost: [`write_correspondence_matrix`] writes
//! every value once, in order, and on x86-64 with AVX writes large matrices with
//! streaming (non-temporal) stores, which do not read the destination's cache lines
//! first. The plain path (zeros, then the weights) is the definition; the streaming
//! one is tested equal to it.

use crate::lanes;

/// Matrices of at least this many values are written with streaming stores (where
/// the CPU has AVX, [`lanes::matrix`]): below it the destination may be read back
/// from the cache soon.
const STREAM_FROM: usize = 1 << 16;

/// Writes the `n x vertex_count` correspondence matrix of `n` points into `out`
/// (row-major, every value written: whatever `out` held is replaced): point `r`'s
/// weights `weights[r]` at columns `vertices[r]`, zeros elsewhere; where a triangle
/// repeats a vertex, the later weight stays (the official assignment order).
///
/// Panics if `out` does not hold `n x vertex_count` values or a vertex is not below
/// `vertex_count` (the caller's arrays are made from the same mesh).
pub fn write_correspondence_matrix(
    out: &mut [f32],
    vertex_count: usize,
    vertices: &[[u32; 3]],
    weights: &[[f32; 3]],
) {
    let entries = matrix_entries(vertex_count, vertices, weights);
    assert_eq!(
        out.len(),
        vertices.len() * vertex_count,
        "a {} x {vertex_count} matrix",
        vertices.len()
    );
    if out.len() >= STREAM_FROM {
        lanes::matrix::write_streamed(out, &entries);
    } else {
        lanes::matrix::write_plain(out, &entries);
    }
}

/// Turns `out`, which holds the matrix of `previous` (zeros but at `previous`'s
/// columns, as [`write_correspondence_matrix`] left it), into the matrix of
/// `vertices` and `weights`: `previous`'s columns set to zero, then the new weights
/// written, about 24 bytes a row instead of the whole row. The result is bit for bit
/// what [`write_correspondence_matrix`] writes, provided `out` held only `previous`'s
/// values (the caller's promise: anything else written into `out` stays).
///
/// Panics as [`write_correspondence_matrix`] does, and if `previous` is not one triple
/// a row with columns below `vertex_count`.
pub fn rewrite_correspondence_matrix(
    out: &mut [f32],
    vertex_count: usize,
    previous: &[[u32; 3]],
    vertices: &[[u32; 3]],
    weights: &[[f32; 3]],
) {
    assert_eq!(
        out.len(),
        vertices.len() * vertex_count,
        "a {} x {vertex_count} matrix",
        vertices.len()
    );
    assert_eq!(
        previous.len(),
        vertices.len(),
        "a previous triple for each row"
    );
    assert_eq!(
        weights.len(),
        vertices.len(),
        "a weight triple for each point"
    );
    if vertices.is_empty() {
        return;
    }
    for (r, row) in out.chunks_exact_mut(vertex_count).enumerate() {
        for &id in &previous[r] {
            assert!(
                (id as usize) < vertex_count,
                "previous vertex {id} of a {vertex_count}-vertex mesh"
            );
            row[id as usize] = 0.0;
        }
        // The three columns assigned in turn: a repeated vertex keeps the later weight.
        for (&id, &w) in vertices[r].iter().zip(&weights[r]) {
            assert!(
                (id as usize) < vertex_count,
                "vertex {id} of a {vertex_count}-vertex mesh"
            );
            row[id as usize] = w;
        }
    }
}

/// The matrix's non-zero candidates as `(position, weight)` in increasing position,
/// one per position (the later of a row's equal columns).
fn matrix_entries(
    vertex_count: usize,
    vertices: &[[u32; 3]],
    weights: &[[f32; 3]],
) -> Vec<(usize, f32)> {
    assert_eq!(
        vertices.len(),
        weights.len(),
        "a weight triple for each point"
    );
    let mut entries = Vec::with_capacity(3 * vertices.len());
    for (r, (ids, w)) in vertices.iter().zip(weights).enumerate() {
        // The row's distinct columns, each with its last weight, then in column order.
        let mut row = [(0usize, 0f32); 3];
        let mut len = 0;
        for (&id, &wk) in ids.iter().zip(w) {
            let id = id as usize;
            assert!(
                id < vertex_count,
                "vertex {id} of a {vertex_count}-vertex mesh"
            );
            match row[..len].iter_mut().find(|(c, _)| *c == id) {
                Some(e) => e.1 = wk,
                None => {
                    row[len] = (id, wk);
                    len += 1;
                }
            }
        }
        let row = &mut row[..len];
        row.sort_unstable_by_key(|&(c, _)| c);
        entries.extend(row.iter().map(|&(c, wk)| (r * vertex_count + c, wk)));
    }
    entries
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lanes::matrix::write_plain;

    fn plain(n: usize, v: usize, ids: &[[u32; 3]], w: &[[f32; 3]]) -> Vec<f32> {
        let mut m = vec![f32::NAN; n * v];
        write_plain(&mut m, &matrix_entries(v, ids, w));
        m
    }

    #[test]
    fn every_value_is_written_with_the_weights_in_their_columns() {
        // By hand: two points of a 5-vertex mesh, the second triangle repeating vertex 4
        // (its last weight, 0.25, stays, as the official assignments leave it).
        let ids = [[2, 0, 1], [4, 3, 4]];
        let w = [[0.5, 0.25, 0.25], [0.5, 0.25, 0.25]];
        let mut m = vec![7.0f32; 10];
        write_correspondence_matrix(&mut m, 5, &ids, &w);
        assert_eq!(m, [0.25, 0.25, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.25, 0.25]);
        assert_eq!(plain(2, 5, &ids, &w), m);
    }

    #[test]
    fn rewriting_over_the_previous_matrix_gives_the_written_one() {
        // Random matrices written in turn into one buffer, each over the last (its
        // repeated vertices and negative zeros included): bit for bit the plain matrix
        // of each, so the previous one's columns were all cleared.
        let mut r = arkit_core::Rng::new(11);
        let (n, v) = (97usize, 1220usize);
        let draw = |r: &mut arkit_core::Rng| {
            let ids: Vec<[u32; 3]> = (0..n)
                .map(|_| {
                    let a = r.below(v as u64) as u32;
                    [
                        a,
                        r.below(v as u64) as u32,
                        if r.below(4) == 0 {
                            a
                        } else {
                            r.below(v as u64) as u32
                        },
                    ]
                })
                .collect();
            let w: Vec<[f32; 3]> = (0..n)
                .map(|_| {
                    [0; 3].map(|_| {
                        if r.below(9) == 0 {
                            -0.0
                        } else {
                            r.uniform(-1.0, 1.0) as f32
                        }
                    })
                })
                .collect();
            (ids, w)
        };
        let (mut prev, w) = draw(&mut r);
        let mut out = vec![f32::NAN; n * v];
        write_correspondence_matrix(&mut out, v, &prev, &w);
        for round in 0..6 {
            let (ids, w) = draw(&mut r);
            rewrite_correspondence_matrix(&mut out, v, &prev, &ids, &w);
            let want = plain(n, v, &ids, &w);
            assert!(
                out.iter()
                    .zip(&want)
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "round {round}"
            );
            prev = ids;
        }
    }

    #[test]
    fn streaming_writes_the_plain_matrix_at_every_alignment() {
        // Matrices large enough to stream, at every float offset from a 32-byte
        // boundary, over old values that are not zero: bit for bit the plain matrix.
        let mut r = arkit_core::Rng::new(3);
        for (n, v) in [(64usize, 1220usize), (57, 1201), (200, 331)] {
            let ids: Vec<[u32; 3]> = (0..n)
                .map(|_| [0; 3].map(|_| r.below(v as u64) as u32))
                .collect();
            let w: Vec<[f32; 3]> = (0..n)
                .map(|_| [0; 3].map(|_| r.uniform(-1.0, 1.0) as f32))
                .collect();
            let want = plain(n, v, &ids, &w);
            let mut backing = vec![f32::NAN; n * v + 16];
            for shift in 0..8 {
                let out = &mut backing[shift..shift + n * v];
                write_correspondence_matrix(out, v, &ids, &w);
                assert!(
                    out.iter()
                        .zip(&want)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{n} x {v} at +{shift}"
                );
            }
        }
    }
}
