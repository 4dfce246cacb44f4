#!/usr/bin/env python3
"""Write the fuzz targets' seed inputs into fuzz/corpus/<target>/seed-* (small, valid or
nearly valid files of each format, so libFuzzer starts past the format's first checks).
Needs numpy; the landmark and fit seeds take a MediaPipe result and a `trainer fit-pose`
fit.json as arguments (optional). Run from the repository root:

    python3 fuzz/make_seeds.py [KP.json FIT.json]
"""
import io, json, os, struct, sys, zlib
import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "corpus")


def put(target, name, data):
    d = os.path.join(ROOT, target)
    os.makedirs(d, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(d, "seed-" + name), "wb") as f:
        f.write(data)


def npz(arrays, compressed=False):
    b = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(b, **arrays)
    return b.getvalue()


def safetensors(meta, tensors):
    header, blob = {"__metadata__": meta}, b""
    for name, arr in tensors.items():
        a = np.asarray(arr, dtype="<f4")
        header[name] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [len(blob), len(blob) + a.nbytes]}
        blob += a.tobytes()
    h = json.dumps(header).encode()
    return struct.pack("<Q", len(h)) + h + blob


def png(w, h, color_type, bit_depth, rows):
    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)
    raw = b"".join(b"\0" + r for r in rows)
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, bit_depth, color_type, 0, 0, 0))
    if color_type == 3:
        out += chunk(b"PLTE", bytes([255, 0, 0, 0, 255, 0]))
    return out + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


# npz: dtypes, orders, compression.
put("npz", "dtypes.npz", npz({"a": np.arange(6, dtype="<f4").reshape(2, 3), "b": np.arange(3, dtype="<f8"),
                             "c": np.arange(4, dtype="<i8"), "d": np.arange(2, dtype="<u4")}))
put("npz", "compressed.npz", npz({"poses": np.zeros((2, 3), "<f4"), "betas": np.ones(4, ">f8")}, compressed=True))
put("npz", "fortran.npz", npz({"f": np.asfortranarray(np.arange(6, dtype="<f4").reshape(2, 3))}))

# body_model: a 3-vertex body in the SMPL layout.
nv, J = 3, 24
kin = np.stack([np.array([-1] + [max(0, j - 1) for j in range(1, J)]), np.arange(J)]).astype("<i8")
body = {"v_template": np.eye(3, dtype="<f4"), "f": np.array([[0, 1, 2]], "<u4"),
        "weights": np.full((nv, J), 1.0 / J, "<f4"), "J_regressor": np.full((J, nv), 1.0 / nv, "<f4"),
        "kintree_table": kin, "shapedirs": np.zeros((nv, 3, 2), "<f4"), "posedirs": np.zeros((nv, 3, 207), "<f4")}
put("body_model", "tiny_body.npz", npz(body))
put("body_model", "tiny_body_uv.npz", npz({**body, "vt": np.zeros((3, 2), "<f4"), "ft": np.array([[0, 1, 2]], "<u4")}, compressed=True))

# motion: an AMASS-like clip, SMPL and SMPL-H widths.
put("motion", "smpl.npz", npz({"poses": np.full((3, 72), 0.1, "<f8"), "trans": np.zeros((3, 3), "<f8"),
                               "mocap_framerate": np.array(30.0), "betas": np.zeros(16, "<f8")}))
put("motion", "smplh.npz", npz({"poses": np.zeros((2, 156), "<f4"), "trans": np.zeros((2, 3), "<f4"),
                                "mocap_frame_rate": np.array(60.0, "<f4")}, compressed=True))

# safetensors / checkpoint: the tiny generator's header, an inverted avatar's, a discriminator's.
tiny = {"name": "tiny", "z_dim": 16, "w_dim": 16, "mapping_layers": 2, "mapping_lr_mul": 0.01, "w_avg_beta": 0.998,
        "plane_res": 16, "plane_channels": 8, "channel_base": 256, "channel_max": 16, "decoder_hidden": 16,
        "texture_features": 8, "tet_res": 24, "template_res": 64}
gen_meta = {"format": "getavatar-generator/1", "config": json.dumps(tiny)}
gen = safetensors(gen_meta, {"latent_modes/geo": np.zeros((2, 16)), "latent_modes/tex": np.zeros((2, 16))})
put("safetensors", "generator.safetensors", gen)
put("checkpoint", "generator.safetensors", gen)
photo_meta = {"res": 16, "world_to_camera": np.eye(4).flatten().tolist(),
              "body": {"pose": [[0.0, 0.0, 0.0]] * 24, "betas": [0.0] * 10}}
put("checkpoint", "inverted.safetensors", safetensors({**gen_meta, "inversion/photo": json.dumps(photo_meta)},
    {"inversion/w_geo": np.zeros((1, 7, 16)), "inversion/w_tex": np.zeros((1, 7, 16)),
     "inversion/photo_rgb": np.zeros((16, 16, 3)), "inversion/photo_mask": np.ones((16, 16))}))
dcfg = {"resolution": 8, "channel_base": 32, "channel_max": 4, "c_dim": 16, "cmap_dim": 4, "mapping_layers": 1, "mbstd_group": 2}
put("checkpoint", "discriminator.safetensors", safetensors(
    {"format": "getavatar-discriminator/1", "discriminator": json.dumps(dcfg)}, {"d0/b4.fc.bias": np.zeros(4)}))
put("safetensors", "empty.safetensors", safetensors({}, {}))

# pose_library: two poses of the builtin file's layout.
lib = json.load(open(os.path.join(os.path.dirname(ROOT), "..", "assets", "poses", "poses.json")))
small = dict(lib)
for k, v in lib.items():
    if isinstance(v, list):
        small[k] = v[:2]
put("pose_library", "two_poses.json", json.dumps(small))

# dataset_labels: one label of 98 numbers.
put("dataset_labels", "one.json", json.dumps({"labels": {"0000/000.png": [1.0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, -2.3, 0, 0, 0, 1] + [0.0] * 82}}))

# scan: OBJ, MTL, SMPL parameters.
put("scan", "quad.obj", "mtllib scan.mtl\no scan\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"
    "vn 0 0 1\ng body\nusemtl skin\nf 1/1/1 2/2/1 3/3/1 4/4/1\ng shirt\nf -4 -3 -2\n")
put("scan", "scan.mtl", "newmtl skin\nKd 0.8 0.6 0.5\nmap_Kd scan.png\n")
put("scan", "smpl.json", json.dumps({"global_orient": [0, 0, 0], "body_pose": [0.0] * 69, "betas": [0.1] * 10,
                                     "transl": [0, 0.2, 0], "scale": 1.0}))

# photo: PNGs of every colour type and bit depth, one JPEG.
put("photo", "rgb8.png", png(2, 2, 2, 8, [bytes(6), bytes([255] * 6)]))
put("photo", "rgba8.png", png(2, 1, 6, 8, [bytes([255, 0, 0, 255, 0, 0, 0, 0])]))
put("photo", "grey16.png", png(1, 2, 0, 16, [b"\xff\xff", b"\x00\x01"]))
put("photo", "palette.png", png(2, 1, 3, 8, [b"\x00\x01"]))
# The JPEG (8×8, baseline, 775 bytes) was made once by headless Chromium (a Playwright JPEG
# screenshot of an 8×8 page with a red→blue gradient) and is kept as it is.

# landmarks and body_fit: a real detector result and fit when given, else synthetic.
marks = [{"x": 0.5 + 0.01 * i, "y": 0.2 + 0.015 * i, "z": 0.0, "visibility": 0.9} for i in range(33)]
put("landmarks", "synthetic.json", json.dumps({"poseLandmarks": marks, "poseWorldLandmarks": marks,
                                               "segmentationMask": {"width": 2, "height": 1, "data": [0.0, 1.0]}}))
if len(sys.argv) > 2:
    kp = json.load(open(sys.argv[1]))
    kp.pop("segmentationMask", None)
    put("landmarks", "mediapipe.json", json.dumps(kp))
    put("body_fit", "fit.json", open(sys.argv[2]).read())

# app_command: JSON commands and URL queries.
for i, c in enumerate([
        {"generate": {"seed": 3, "psi": 0.7}}, {"pose": "walk"}, {"joint": {"name": "left_knee", "axis_angle": [0.5, 0, 0]}},
        {"camera": {"yaw": 1.0, "pitch": 0.1, "distance": 2.3}}, {"view": "normal"},
        {"reconstruct": {"res": 64, "steps": 3, "pti_steps": 1, "preview_every": 0}},
        {"photo": {"url": "blob:x"}}, {"open_reconstruction": {"url": "blob:y"}}]):
    put("app_command", f"cmd{i}.json", json.dumps(c))
put("app_command", "query.txt", "seed=7&psi=0.5&pose=walk&view=mask&res=512&yaw=0.3&betas=1,0.5&joint=left_elbow:0,1,0%20")
