"""What `render`'s compact targets encoding saves against plain Arrow types that any
Parquet reader understands, measured on a rendered dataset.

    python python/bench/targets_layout.py DATASET/targets [--repeat 3]

For every `targets/part-K.parquet` it decodes the compact columns with
`arkit_tool.decode_targets` (plain numpy; the layouts of schemas/targets.json: run-length
mask, u16 vertex ids and quantised weights, u32 points, delta-coded float16 UV planes),
writes the same values as plain types (mask as
fixed_size_list<bool>[S*S]; correspondences as list<fixed_size_list<uint16>[3]> and
list<fixed_size_list<uint16>[2]>, the same quantised weights; points list<uint32>; the UV
map as fixed_size_list<fixed_size_list<float16>[3]>[uv*uv], zstd, as pyarrow writes it),
and prints bytes per sample and the time to read a file and have numpy arrays, both ways.
Needs numpy, pyarrow and the arkit_tool package (for its decoder only).
"""

import argparse
import pathlib
import tempfile
import time

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from arkit_tool import decode_targets

BLOBS = ["mask_rle", "corr_vertices", "corr_weights", "points", "uv_map_delta", "full_mask_rle"]


def decode_row(row):
    t = decode_targets(row)
    return {k: t[k] for k in ("mask", "corr_vertices", "points", "uv_map")} | {
        # the stored (quantised) form, as the plain table keeps it
        "corr_weights": np.frombuffer(row["corr_weights"], dtype="<u2").reshape(-1, 2)}


def compact_read(path):
    t = pq.read_table(path)
    return [decode_row(r) for r in t.select(BLOBS[:-1] + ["crop_size", "uv_size"]).to_pylist()]


def plain_table(rows, s, uv):
    def lists(key, width, typ):
        flat = np.concatenate([r[key].reshape(-1) for r in rows])
        offsets = np.cumsum([0] + [len(r[key]) for r in rows]).astype(np.int32)
        inner = pa.FixedSizeListArray.from_arrays(pa.array(flat, type=typ), width)
        return pa.ListArray.from_arrays(pa.array(offsets), inner)

    mask = pa.FixedSizeListArray.from_arrays(
        pa.array(np.concatenate([r["mask"].reshape(-1) for r in rows])), s * s)
    uv_flat = np.concatenate([r["uv_map"].reshape(-1) for r in rows])  # texel-major, 3 a texel
    uv_map = pa.FixedSizeListArray.from_arrays(
        pa.FixedSizeListArray.from_arrays(pa.array(uv_flat, type=pa.float16()), 3), uv * uv)
    points_offsets = np.cumsum([0] + [len(r["points"]) for r in rows]).astype(np.int32)
    points = pa.ListArray.from_arrays(
        pa.array(points_offsets), pa.array(np.concatenate([r["points"] for r in rows])))
    return pa.table({
        "mask": mask,
        "corr_vertices": lists("corr_vertices", 3, pa.uint16()),
        "corr_weights": lists("corr_weights", 2, pa.uint16()),
        "points": points,
        "uv_map": uv_map,
    })


def plain_read(path, s, uv):
    t = pq.read_table(path)
    n = t.num_rows
    mask = t["mask"].combine_chunks().flatten().to_numpy(zero_copy_only=False).reshape(n, s, s)
    uv_map = t["uv_map"].combine_chunks().flatten().flatten().to_numpy().reshape(n, uv, uv, 3)
    out = []
    for name in ("corr_vertices", "corr_weights", "points"):
        col = t[name].combine_chunks()
        out.append((col.offsets.to_numpy(), col.flatten()))
    return mask, uv_map, out


def timed(f, repeat):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("targets", type=pathlib.Path)
    p.add_argument("--repeat", type=int, default=3)
    a = p.parse_args()
    files = sorted(a.targets.glob("part-*.parquet"))
    assert files, f"no part-*.parquet in {a.targets}"
    n = compact_bytes = plain_bytes = 0
    t_compact = t_plain = 0.0
    per_column = {}
    with tempfile.TemporaryDirectory() as tmp:
        for f in files:
            t = pq.read_table(f)
            if t.num_rows == 0:
                continue
            s, uv = t["crop_size"][0].as_py(), t["uv_size"][0].as_py()
            rows = compact_read(f)
            plain = plain_table(rows, s, uv)
            out = pathlib.Path(tmp) / f.name
            pq.write_table(plain, out, compression="zstd")
            meta = pq.ParquetFile(out).metadata
            for rg in range(meta.num_row_groups):
                for c in range(meta.num_columns):
                    col = meta.row_group(rg).column(c)
                    key = col.path_in_schema.split(".")[0]
                    per_column[key] = per_column.get(key, 0) + col.total_compressed_size
            blob_meta = pq.ParquetFile(f).metadata
            for rg in range(blob_meta.num_row_groups):
                for c in range(blob_meta.num_columns):
                    col = blob_meta.row_group(rg).column(c)
                    if col.path_in_schema in BLOBS:
                        key = "compact " + col.path_in_schema
                        per_column[key] = per_column.get(key, 0) + col.total_compressed_size
            n += t.num_rows
            compact_bytes += f.stat().st_size
            plain_bytes += out.stat().st_size
            t_compact += timed(lambda: compact_read(f), a.repeat)
            t_plain += timed(lambda: plain_read(out, s, uv), a.repeat)
    kib = 1024.0 * n
    print(f"samples: {n} in {len(files)} files (crop {s}, uv {uv})")
    print(f"compact: {compact_bytes / kib:.1f} KiB per sample, read+decode {1e3 * t_compact / n:.3f} ms per sample")
    print(f"plain:   {plain_bytes / kib:.1f} KiB per sample, read {1e3 * t_plain / n:.3f} ms per sample")
    print(f"ratio: plain/compact size {plain_bytes / compact_bytes:.2f}")
    for k in sorted(per_column):
        print(f"  {k}: {per_column[k] / kib:.1f} KiB per sample")


if __name__ == "__main__":
    main()
