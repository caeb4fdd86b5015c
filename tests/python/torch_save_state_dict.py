"""Reads a safetensors file (header and raw little-endian data, parsed here so that only
torch is needed) and writes its tensors with torch.save as a state_dict, each name
prefixed with `module.` as DataParallel saves them. Used by tests/weights.rs.

usage: torch_save_state_dict.py IN.safetensors OUT.pth
"""
import collections
import json
import struct
import sys

import torch

DTYPES = {"F32": torch.float32, "I64": torch.int64, "F16": torch.float16}


def read_safetensors(path):
    with open(path, "rb") as f:
        data = f.read()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    body = data[8 + n :]
    out = collections.OrderedDict()
    for name in sorted(header):
        if name == "__metadata__":
            continue
        info = header[name]
        start, end = info["data_offsets"]
        t = torch.frombuffer(bytearray(body[start:end]), dtype=DTYPES[info["dtype"]])
        out[name] = t.reshape(info["shape"]).clone()
    return out


if __name__ == "__main__":
    state = read_safetensors(sys.argv[1])
    torch.save(collections.OrderedDict(("module." + k, v) for k, v in state.items()), sys.argv[2])
