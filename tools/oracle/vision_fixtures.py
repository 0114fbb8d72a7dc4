"""Generates the vision-layer fixtures under tests/fixtures/vision/.

Synthetic images are written as PNG/JPEG files in many encodings; PIL decodes them (the pixels
lerobot would see), and torch + lerobot compute the expected resize and SmolVLA preprocessing
outputs. Both of torch's float bilinear kernels are covered by running every case with one and
with several torch threads (torch picks its kernel by thread count and output size).

Run in the oracle virtualenv (torch, lerobot, pillow, numpy, safetensors):
    tools/oracle/run.sh vision_fixtures.py [--out tests/fixtures/vision]
"""

import argparse
import io
import json
import os
import re
import struct
import zlib
from importlib.metadata import version

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image, features
from safetensors.numpy import save_file

from lerobot.policies.common.vla_utils import resize_with_pad

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
THREAD_MODES = {"many": 2, "one": 1}


# ---------------------------------------------------------------- synthetic content


def scene(h, w, seed, noise_sigma=6.0):
    """Gradients, sharp edges, a disc and some noise: exercises smooth and high-frequency paths."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 255 * x / max(w - 1, 1)
    g = 255 * y / max(h - 1, 1)
    b = 128 + 127 * np.sin(x / 3.0) * np.cos(y / 5.0)
    img = np.stack([r, g, b], axis=-1)
    img[(x // 8 + y // 8) % 2 == 0] *= 0.5  # checkerboard edges
    disc = (x - w / 2) ** 2 + (y - h / 2) ** 2 < (min(h, w) / 4) ** 2
    img[disc] = [250, 20, 60]
    img += rng.normal(0, noise_sigma, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def noise(h, w, seed, channels=3):
    return np.random.default_rng(seed).integers(0, 256, (h, w, channels), dtype=np.uint8)


# ---------------------------------------------------------------- a small PNG writer
# PIL cannot write 16-bit colour, grey+alpha 16, low-depth grey or interlaced PNGs, so those are
# encoded here. Rows cycle through all five filter types so the decoder's unfiltering is exercised.


def _chunk(kind, data):
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _paeth(a, b, c):
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _filter_rows(rows, bpp):
    out = []
    prev = np.zeros_like(rows[0]) if rows else None
    for i, row in enumerate(rows):
        ftype = i % 5
        r = row.astype(np.int32)
        p = prev.astype(np.int32)
        left = np.concatenate([np.zeros(bpp, np.int32), r[:-bpp]]) if len(r) > bpp else np.zeros_like(r)
        upleft = np.concatenate([np.zeros(bpp, np.int32), p[:-bpp]]) if len(p) > bpp else np.zeros_like(p)
        if len(r) <= bpp:
            left = np.zeros_like(r)
            upleft = np.zeros_like(p)
        pred = [np.zeros_like(r), left, p, (left + p) // 2, _paeth(left, p, upleft)][ftype]
        out.append(bytes([ftype]) + ((r - pred) & 0xFF).astype(np.uint8).tobytes())
        prev = row
    return out


def _pack_rows(samples, depth):
    """samples: (h, w*channels) integers -> list of byte rows at `depth` bits per sample."""
    rows = []
    for row in samples:
        if depth == 16:
            rows.append(np.frombuffer(row.astype(">u2").tobytes(), np.uint8))
        elif depth == 8:
            rows.append(row.astype(np.uint8))
        else:
            per = 8 // depth
            padded = np.concatenate([row, np.zeros((-len(row)) % per, row.dtype)]).reshape(-1, per)
            shifts = np.array([8 - depth * (k + 1) for k in range(per)])
            rows.append((padded.astype(np.uint32) << shifts).sum(axis=1).astype(np.uint8))
    return rows


ADAM7 = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]


def write_png(samples, color_type, depth, palette=None, trns=None, interlace=False):
    """samples: (h, w, channels) array of raw sample values."""
    h, w, ch = samples.shape
    bpp = max(1, ch * depth // 8)
    if interlace:
        stream = b""
        for x0, y0, dx, dy in ADAM7:
            sub = samples[y0::dy, x0::dx]
            if sub.size == 0:
                continue
            stream += b"".join(_filter_rows(_pack_rows(sub.reshape(sub.shape[0], -1), depth), bpp))
    else:
        stream = b"".join(_filter_rows(_pack_rows(samples.reshape(h, -1), depth), bpp))
    out = b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, color_type, 0, 0, int(interlace)))
    if palette is not None:
        out += _chunk(b"PLTE", np.asarray(palette, np.uint8).tobytes())
    if trns is not None:
        out += _chunk(b"tRNS", trns)
    return out + _chunk(b"IDAT", zlib.compress(stream, 9)) + _chunk(b"IEND", b"")


def pil_bytes(img, fmt, **kw):
    buf = io.BytesIO()
    img.save(buf, fmt, **kw)
    return buf.getvalue()


# ---------------------------------------------------------------- fixture sets


def image_files():
    """name -> encoded bytes. Names carry the extension the C++ test uses to pick the file."""
    files = {}
    rgb = scene(37, 53, 1)
    pil_rgb = Image.fromarray(rgb)
    files["rgb8.png"] = pil_bytes(pil_rgb, "PNG")
    rgba = np.concatenate([rgb, noise(37, 53, 2, 1)], axis=-1)
    files["rgba8.png"] = pil_bytes(Image.fromarray(rgba, "RGBA"), "PNG")
    gray = rgb[..., 1]
    files["gray8.png"] = pil_bytes(Image.fromarray(gray, "L"), "PNG")
    files["gray_alpha8.png"] = pil_bytes(Image.fromarray(np.stack([gray, rgb[..., 0]], -1), "LA"), "PNG")
    files["gray1.png"] = pil_bytes(Image.fromarray(gray > 120), "PNG")
    pal = pil_rgb.quantize(colors=200)
    files["palette8.png"] = pil_bytes(pal, "PNG")
    files["palette8_trns.png"] = pil_bytes(pal, "PNG", transparency=3)
    files["palette4.png"] = pil_bytes(pil_rgb.quantize(colors=16), "PNG", bits=4)

    rng = np.random.default_rng(7)
    g16 = rng.integers(0, 65536, (23, 31, 1)).astype(np.int64)
    g16[:, :8] = rng.integers(0, 300, (23, 8, 1))  # around PIL's clip at 255
    files["gray16.png"] = write_png(g16, 0, 16)
    files["gray16_interlaced.png"] = write_png(g16, 0, 16, interlace=True)
    files["rgb16.png"] = write_png(rng.integers(0, 65536, (19, 29, 3)), 2, 16)
    files["rgba16.png"] = write_png(rng.integers(0, 65536, (19, 29, 4)), 6, 16)
    files["gray_alpha16.png"] = write_png(rng.integers(0, 65536, (19, 29, 2)), 4, 16)
    files["gray2.png"] = write_png(rng.integers(0, 4, (13, 21, 1)), 0, 2)
    files["gray4.png"] = write_png(rng.integers(0, 16, (13, 21, 1)), 0, 4)
    files["gray4_interlaced.png"] = write_png(rng.integers(0, 16, (13, 21, 1)), 0, 4, interlace=True)
    files["rgb8_interlaced.png"] = write_png(rgb.astype(np.int64), 2, 8, interlace=True)
    files["rgba8_interlaced.png"] = write_png(rgba.astype(np.int64), 6, 8, interlace=True)
    small_pal = rng.integers(0, 256, (5, 3))
    files["palette2_short.png"] = write_png(rng.integers(0, 4, (9, 11, 1)), 3, 2, palette=small_pal[:3])
    files["palette1.png"] = write_png(rng.integers(0, 2, (9, 11, 1)), 3, 1, palette=small_pal[:2])
    files["palette8_interlaced.png"] = write_png(rng.integers(0, 5, (17, 19, 1)), 3, 8, palette=small_pal)
    files["rgb8_trns.png"] = write_png(rgb.astype(np.int64), 2, 8, trns=struct.pack(">HHH", 10, 20, 30))
    files["tiny_1x1.png"] = write_png(np.array([[[200, 100, 50]]]), 2, 8)

    big = scene(480, 640, 3, noise_sigma=0.0)  # noiseless, so the file stays small
    files["scene_480x640.png"] = pil_bytes(Image.fromarray(big), "PNG", optimize=True)

    jrgb = Image.fromarray(scene(45, 61, 4))  # odd size: partial MCUs on both axes
    files["q90_444.jpg"] = pil_bytes(jrgb, "JPEG", quality=90, subsampling=0)
    files["q85_422.jpg"] = pil_bytes(jrgb, "JPEG", quality=85, subsampling=1)
    files["q75_420.jpg"] = pil_bytes(jrgb, "JPEG", quality=75, subsampling=2)
    files["q75_420_progressive.jpg"] = pil_bytes(jrgb, "JPEG", quality=75, subsampling=2, progressive=True)
    files["q95_444_optimized.jpg"] = pil_bytes(jrgb, "JPEG", quality=95, subsampling=0, optimize=True)
    files["gray.jpg"] = pil_bytes(jrgb.convert("L"), "JPEG", quality=80)
    files["gray_progressive.jpg"] = pil_bytes(jrgb.convert("L"), "JPEG", quality=80, progressive=True)
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 CW": PIL's open/convert ignores it, and so must we
    files["exif_rotated.jpg"] = pil_bytes(jrgb, "JPEG", quality=85, exif=exif.tobytes())
    files["camera_240x320.jpg"] = pil_bytes(Image.fromarray(scene(240, 320, 5)), "JPEG", quality=80)
    return files


def bad_files(good):
    """name -> bytes that PIL also refuses (checked below); the C++ decoder must throw on each."""
    png, jpg = good["rgb8.png"], good["q75_420.jpg"]
    bad = {}
    bad["truncated.png"] = png[: len(png) // 2]
    bad["truncated.jpg"] = jpg[: len(jpg) // 2]
    bad["truncated_progressive.jpg"] = good["q75_420_progressive.jpg"][: len(good["q75_420_progressive.jpg"]) * 2 // 3]
    bad["header_only.jpg"] = jpg[:200]
    bad["signature_only.png"] = png[:8]
    corrupt = bytearray(png)
    idat = corrupt.find(b"IDAT")
    corrupt[idat + 20] ^= 0xFF  # breaks the chunk CRC
    bad["bad_crc.png"] = bytes(corrupt)
    # Claims 20000 x 20000 pixels (400 MP) with a valid header: must be refused before allocation.
    bad["bomb_400mp.png"] = (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", struct.pack(">IIBBBBB", 20000, 20000, 8, 2, 0, 0, 0))
        + _chunk(b"IDAT", zlib.compress(b"\x00" * 1000))
        + _chunk(b"IEND", b"")
    )
    sof = jpg.find(b"\xff\xc0")
    bomb = bytearray(jpg)
    bomb[sof + 5 : sof + 9] = struct.pack(">HH", 60000, 60000)  # height, width in SOF0
    bad["bomb_3600mp.jpg"] = bytes(bomb)
    bad["cmyk.jpg"] = pil_bytes(Image.fromarray(noise(16, 16, 9, 4), "CMYK"), "JPEG")
    bad["not_an_image.gif"] = pil_bytes(Image.fromarray(noise(8, 8, 10)), "GIF")
    bad["random.bin"] = noise(1, 64, 11, 1).tobytes()
    bad["empty.png"] = b""
    return bad


UNSUPPORTED_BY_DESIGN = {"cmyk.jpg": "CMYK JPEG", "not_an_image.gif": "only PNG and JPEG are read"}


def pil_rgb(data):
    with Image.open(io.BytesIO(data)) as im:
        return np.array(im.convert("RGB"))


def pil_error(data):
    try:
        with Image.open(io.BytesIO(data)) as im:
            im.convert("RGB")
    except Exception as e:  # noqa: BLE001 - any refusal counts
        # drop object addresses so regeneration stays byte-identical
        return re.sub(r" at 0x[0-9a-f]+", "", f"{type(e).__name__}: {e}")
    return None


def save(tensors, out, name, fixture_meta):
    """All metadata goes under one key, "fixture", as JSON with sorted keys: the safetensors writer
    orders several metadata keys differently from run to run, and regeneration must be byte-identical."""
    save_file(tensors, os.path.join(out, name), metadata={"fixture": json.dumps(fixture_meta, sort_keys=True)})


def with_threads(n, fn):
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        return fn()
    finally:
        torch.set_num_threads(old)


# (name, channels, in_h, in_w, out_h, out_w): up, down, odd, non-integer ratios, identity, 1 pixel.
RESIZE_CASES = [
    ("down2x_48x64_24x32", 3, 48, 64, 24, 32),
    ("up_17x23_32x32", 3, 17, 23, 32, 32),
    ("down_60x40_32x21", 3, 60, 40, 32, 21),
    ("up_30x40_60x90", 3, 30, 40, 60, 90),
    ("mixed_33x47_150x37", 3, 33, 47, 150, 37),
    ("down_50x90_41x67", 3, 50, 90, 41, 67),
    ("down_70x95_37x97", 3, 70, 95, 37, 97),
    ("tiny_7x5_3x2", 3, 7, 5, 3, 2),
    ("identity_40x60", 3, 40, 60, 40, 60),
    ("one_pixel_1x1_5x7", 3, 1, 1, 5, 7),
    ("column_9x1_70x1", 3, 9, 1, 70, 1),
    ("row_same_height_20x30_20x90", 3, 20, 30, 20, 90),
    ("mono_25x35_80x90", 1, 25, 35, 80, 90),
    ("four_ch_25x35_80x90", 4, 25, 35, 80, 90),
    ("four_ch_25x35_30x40", 4, 25, 35, 30, 40),
]

# (name, source, out_h, out_w); source is an image file name or "noise:HxW:seed".
PREPROCESS_CASES = [
    ("noise_96x128_to_64x64", "noise:96x128:21", 64, 64),
    ("noise_120x80_to_64x64", "noise:120x80:22", 64, 64),
    ("noise_17x23_to_32x32", "noise:17x23:23", 32, 32),
    ("scene_480x640_to_128x128", "scene_480x640.png", 128, 128),
    ("camera_240x320_to_64x96", "camera_240x320.jpg", 64, 96),
    ("noise_30x50_to_84x84", "noise:30x50:24", 84, 84),
    ("noise_33x47_to_72x120", "noise:33x47:25", 72, 120),
    ("noise_64x64_passthrough", "noise:64x64:26", 64, 64),
    ("noise_40x1_to_64x64", "noise:40x1:27", 64, 64),
    ("noise_1x1_to_64x64", "noise:1x1:28", 64, 64),
    ("noise_64x32_to_64x64", "noise:64x32:29", 64, 64),
]

# Aspect ratios so extreme that a side would resize to 0 pixels: torch refuses them.
PREPROCESS_ERRORS = [("noise_1x1000_to_64x64", 1, 1000, 64, 64), ("noise_300x2_to_64x64", 300, 2, 64, 64)]


def store_modes(tensors, prefix, ys):
    """threads_many always; threads_one only where torch's single-thread kernel rounded differently
    (the C++ test then falls back to threads_many), which keeps the fixtures small."""
    tensors[f"{prefix}/threads_many"] = np.ascontiguousarray(ys["many"])
    if not np.array_equal(ys["one"].view(np.uint32), ys["many"].view(np.uint32)):
        tensors[f"{prefix}/threads_one"] = np.ascontiguousarray(ys["one"])


def smolvla_reference(img_u8, out_h, out_w):
    """lerobot's path: uint8 HWC -> float/255 -> CHW -> resize_with_pad(pad_value=0) -> *2-1."""
    x = torch.from_numpy(img_u8).type(torch.float32) / 255
    x = x.permute(2, 0, 1).contiguous().unsqueeze(0)
    y = resize_with_pad(x, out_h, out_w, pad_value=0)
    return (y * 2.0 - 1.0)[0].numpy()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(REPO, "tests", "fixtures", "vision"))
    args = ap.parse_args()
    out = args.out
    for sub in ("images", "bad"):
        os.makedirs(os.path.join(out, sub), exist_ok=True)

    versions = {
        "torch": torch.__version__,
        "lerobot": version("lerobot"),
        "pillow": version("pillow"),
        "numpy": np.__version__,
        "safetensors": version("safetensors"),
        "libjpeg_turbo": features.version("libjpeg_turbo") or "unknown",
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
    }

    # Decoding: every file with PIL's RGB pixels.
    files = image_files()
    decoded = {}
    for name, data in sorted(files.items()):
        with open(os.path.join(out, "images", name), "wb") as f:
            f.write(data)
        decoded[f"decoded/{name}"] = np.ascontiguousarray(pil_rgb(data))
    # The big PNG's pixels (900 KB raw) are not stored: it is checked through the preprocessing case
    # built on it, and PNG decoding is covered pixel for pixel by the small files.
    big_png = decoded.pop("decoded/scene_480x640.png")
    bad = bad_files(files)
    bad_meta = {}
    for name, data in sorted(bad.items()):
        with open(os.path.join(out, "bad", name), "wb") as f:
            f.write(data)
        err = pil_error(data)
        if name in UNSUPPORTED_BY_DESIGN:
            bad_meta[name] = f"PIL decodes it; Tether refuses it as unsupported ({UNSUPPORTED_BY_DESIGN[name]})"
        else:
            assert err is not None, f"PIL accepted {name}; it is not a refusal case"
            bad_meta[name] = err
    save(decoded, out, "decode.safetensors", {"versions": versions, "bad_files": bad_meta})

    # Bilinear resize on float32 CHW, as F.interpolate computes it.
    tensors, cases = {}, []
    rng = np.random.default_rng(1234)
    for name, c, h, w, oh, ow in RESIZE_CASES:
        x = rng.uniform(-1.0, 2.0, (c, h, w)).astype(np.float32)
        tensors[f"resize/{name}/input"] = x
        ys = {}
        for mode, n in THREAD_MODES.items():
            ys[mode] = with_threads(n, lambda: F.interpolate(torch.from_numpy(x)[None], size=(oh, ow), mode="bilinear",
                                                             align_corners=False, antialias=False)[0].numpy())
        store_modes(tensors, f"resize/{name}", ys)
        cases.append({"name": name, "channels": c, "in": [h, w], "out": [oh, ow],
                      "threads_differ": bool(f"resize/{name}/threads_one" in tensors)})
    save(tensors, out, "resize.safetensors", {"versions": versions, "cases": cases, "thread_modes": THREAD_MODES})

    # Full SmolVLA image preprocessing from uint8 pixels.
    tensors, cases = {}, []
    for name, source, oh, ow in PREPROCESS_CASES:
        if source.startswith("noise:"):
            _, size, seed = source.split(":")
            h, w = map(int, size.split("x"))
            img = noise(h, w, int(seed))
            tensors[f"preprocess/{name}/image"] = img
        else:
            img = big_png if source == "scene_480x640.png" else decoded[f"decoded/{source}"]
        ys = {mode: with_threads(n, lambda: smolvla_reference(img, oh, ow)) for mode, n in THREAD_MODES.items()}
        store_modes(tensors, f"preprocess/{name}", ys)
        cases.append({"name": name, "source": source, "out": [oh, ow],
                      "threads_differ": bool(f"preprocess/{name}/threads_one" in tensors)})
    errors = []
    for name, h, w, oh, ow in PREPROCESS_ERRORS:
        try:
            smolvla_reference(noise(h, w, 0), oh, ow)
        except RuntimeError as e:
            errors.append({"name": name, "in": [h, w], "out": [oh, ow], "torch_error": str(e).splitlines()[0]})
        else:
            raise AssertionError(f"torch accepted {name}")
    save(tensors, out, "preprocess.safetensors",
         {"versions": versions, "cases": cases, "errors": errors, "thread_modes": THREAD_MODES})

    total = 0
    for root, _, names in os.walk(out):
        total += sum(os.path.getsize(os.path.join(root, n)) for n in names)
    print(f"wrote {out}: {total / 1e6:.2f} MB; versions {versions}")


if __name__ == "__main__":
    main()
