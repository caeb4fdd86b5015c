"""Writes the committed seeds of the `torch_pickle` fuzz target (fuzz/corpus/torch_pickle):
real `torch.save(state_dict)` archives made with torch, and hostile pickles (as bare
`data.pkl` bytes and inside a torch-like zip). Replayed on stable by
crates/arkit-core/tests/fuzz_corpus.rs; `real.pth` is also read, value for value, by
the unit tests of crates/arkit-core/src/torch_pickle.rs.

usage: torch_pickle_seeds.py OUT_DIR
"""
import collections
import io
import os
import struct
import sys
import zipfile

import torch


def torch_like_zip(pickle_bytes, storages=()):
    """A zip laid out as torch.save lays it out, with `pickle_bytes` as its data.pkl."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        z.writestr("archive/data.pkl", pickle_bytes)
        z.writestr("archive/byteorder", b"little")
        for key, data in storages:
            z.writestr(f"archive/data/{key}", data)
        z.writestr("archive/version", b"3\n")
    return buf.getvalue()


def nested_tuples(depth):
    """EMPTY_TUPLE, then TUPLE1 `depth` times: a tuple nested `depth` deep."""
    return b"\x80\x02)" + b"\x85" * depth + b"."


def nested_marks(depth):
    return b"\x80\x02" + b"(" * depth + b")."


def memo_doubling(times):
    """One memo entry replaced `times` times by a pair of itself: 2**times leaves if copied."""
    out = b"\x80\x02X\x01\x00\x00\x00aq\x000"
    for _ in range(times):
        out += b"h\x00h\x00\x86q\x000"
    return out + b"h\x00."


def main(out):
    os.makedirs(out, exist_ok=True)
    w = lambda name, data: open(os.path.join(out, name), "wb").write(data)
    sd = collections.OrderedDict()
    sd["a.weight"] = torch.arange(6, dtype=torch.float32).reshape(2, 3)
    sd["a.num_batches_tracked"] = torch.tensor(7)
    # A transposed view: strides (1, 4), read through the strides.
    sd["b"] = torch.arange(12, dtype=torch.float32).reshape(3, 4).t()
    sd["c.half"] = torch.tensor([1.5, -2.0], dtype=torch.float16)
    torch.save(sd, os.path.join(out, "real.pth"))
    net = torch.nn.Sequential(torch.nn.Conv1d(2, 3, 1), torch.nn.BatchNorm1d(3))
    torch.save(net.state_dict(), os.path.join(out, "module.pth"))
    buf = io.BytesIO()
    torch.save(net.state_dict(), buf)
    with zipfile.ZipFile(buf) as z:
        name = [n for n in z.namelist() if n.endswith("/data.pkl")][0]
        w("module.pkl", z.read(name))
    extra = net.state_dict()
    extra["epoch"] = 5
    torch.save(extra, os.path.join(out, "non_tensor_entry.pth"))
    w("nested_tuples.pkl", nested_tuples(1000))
    w("nested_marks.pkl", nested_marks(1000))
    w("memo_doubling.pkl", memo_doubling(40))
    w("memo_doubling.pth", torch_like_zip(memo_doubling(40)))
    w("nested_tuples.pth", torch_like_zip(nested_tuples(1000)))
    # A tensor whose declared size reaches beyond its storage.
    p = (b"\x80\x02ccollections\nOrderedDict\n)R(X\x01\x00\x00\x00xctorch._utils\n_rebuild_tensor_v2\n"
         b"((X\x07\x00\x00\x00storagectorch\nFloatStorage\nX\x01\x00\x00\x000X\x03\x00\x00\x00cpuK\x02tQ"
         b"K\x00K\x03\x85K\x01\x85\x89ccollections\nOrderedDict\n)RtRu.")
    w("beyond_storage.pth", torch_like_zip(p, [("0", struct.pack("<2f", 1.0, 2.0))]))


if __name__ == "__main__":
    main(sys.argv[1])
