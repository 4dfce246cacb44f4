#!/usr/bin/env python3
"""Inception-v3 (FID) weights for `trainer eval --inception`.

  convert   PTH OUT   Convert pytorch-fid's `pt_inception-2015-12-05-6726825d.pth` (a
                      PyTorch state dict) to the safetensors file `trainer eval` reads:
                      every floating-point tensor as F32 under its state-dict key.
  reference OUT       Write the test fixture trainer/tests/fixtures/inception_reference.safetensors:
                      pool3 features computed by pytorch-fid's own `InceptionV3` on
                      deterministic hash-generated weights and inputs (the Rust test
                      regenerates both with the same hash and compares features).

Needs torch (e.g. Debian's python3-torch); `reference` also needs torchvision and
pytorch-fid (`pip download pytorch-fid --no-deps`, then put it on PYTHONPATH).
"""
import json
import math
import struct
import sys

import numpy as np


def write_safetensors(path, tensors, metadata=None):
    """tensors: {name: float32 ndarray}; the standard layout, keys sorted."""
    header, blobs, off = {}, [], 0
    if metadata:
        header["__metadata__"] = {k: str(v) for k, v in metadata.items()}
    for k in sorted(tensors):
        a = np.ascontiguousarray(tensors[k], dtype="<f4")
        b = a.tobytes()
        header[k] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [off, off + len(b)]}
        blobs.append(b)
        off += len(b)
    h = json.dumps(header, separators=(",", ":")).encode()
    h += b" " * (-len(h) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(h)))
        f.write(h)
        for b in blobs:
            f.write(b)


def convert(pth, out):
    import torch

    sd = torch.load(pth, map_location="cpu")
    t = {k: v.float().numpy() for k, v in sd.items() if v.is_floating_point()}
    write_safetensors(out, t, {"source": "pt_inception-2015-12-05"})
    print(f"wrote {out}: {len(t)} tensors, {sum(v.size for v in t.values()):,} values")


# ---- deterministic weights shared with trainer/src/inception.rs (tests) ----

def fnv1a(s):
    h = 0x811C9DC5
    for b in s.encode():
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h


def hash_uniform(name, n):
    """n values in [-1, 1): murmur3's fmix32 of (i·0x9E3779B9) xor fnv1a(name)."""
    with np.errstate(over="ignore"):
        h = np.arange(n, dtype=np.uint32) * np.uint32(0x9E3779B9) ^ np.uint32(fnv1a(name))
        h ^= h >> np.uint32(16)
        h *= np.uint32(0x85EBCA6B)
        h ^= h >> np.uint32(13)
        h *= np.uint32(0xC2B2AE35)
        h ^= h >> np.uint32(16)
    return h.astype(np.float64) / 4294967296.0 * 2.0 - 1.0


def hash_tensor(name, shape):
    n = int(np.prod(shape))
    u = hash_uniform(name, n)
    if name.endswith("conv.weight"):
        fan_in = int(np.prod(shape[1:]))
        v = u * (math.sqrt(3.0) * math.sqrt(2.0 / fan_in))
    elif name.endswith("bn.weight"):
        v = 1.0 + 0.2 * u
    elif name.endswith("bn.bias") or name.endswith("bn.running_mean"):
        v = 0.1 * u
    elif name.endswith("bn.running_var"):
        v = 1.0 + 0.5 * u
    else:
        v = np.zeros(n)
    return v.astype(np.float32).reshape(shape)


def reference(out):
    import torch
    import pytorch_fid.inception as pi

    def hashed_state_dict(*_a, **_k):
        skel = pi._inception_v3(num_classes=1008, aux_logits=False, weights=None)
        for name, blk in [("Mixed_5b", pi.FIDInceptionA(192, pool_features=32)),
                          ("Mixed_5c", pi.FIDInceptionA(256, pool_features=64)),
                          ("Mixed_5d", pi.FIDInceptionA(288, pool_features=64)),
                          ("Mixed_6b", pi.FIDInceptionC(768, channels_7x7=128)),
                          ("Mixed_6c", pi.FIDInceptionC(768, channels_7x7=160)),
                          ("Mixed_6d", pi.FIDInceptionC(768, channels_7x7=160)),
                          ("Mixed_6e", pi.FIDInceptionC(768, channels_7x7=192)),
                          ("Mixed_7b", pi.FIDInceptionE_1(1280)),
                          ("Mixed_7c", pi.FIDInceptionE_2(2048))]:
            setattr(skel, name, blk)
        sd = {}
        for k, v in skel.state_dict().items():
            if k.endswith("num_batches_tracked"):
                sd[k] = torch.zeros_like(v)
            else:
                sd[k] = torch.from_numpy(hash_tensor(k, tuple(v.shape)))
        counted = sum(v.numel() for k, v in sd.items() if ("conv." in k or ".bn." in k) and "num_batches" not in k)
        print(f"conv+bn parameters up to pool3: {counted:,}")
        return sd

    pi.load_state_dict_from_url = hashed_state_dict
    model = pi.InceptionV3([pi.InceptionV3.BLOCK_INDEX_BY_DIM[2048]]).eval()
    shape = (2, 3, 64, 40)
    x = hash_uniform("input", int(np.prod(shape))).astype(np.float32).reshape(shape) * 0.5 + 0.5
    with torch.no_grad():
        f = model(torch.from_numpy(x))[0].reshape(shape[0], -1).numpy()
    write_safetensors(out, {"features": f}, {"input_shape": json.dumps(list(shape))})
    print(f"wrote {out}: features {f.shape}, mean {f.mean():.4f}, std {f.std():.4f}")


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "convert":
        convert(sys.argv[2], sys.argv[3])
    elif len(sys.argv) == 3 and sys.argv[1] == "reference":
        reference(sys.argv[2])
    else:
        sys.exit(__doc__)
