"""Generates the GR00T N1.7 camera-frame fixtures under tests/fixtures/vision/gr00t/.

Everything here runs the real upstream code in the oracle venv:
  - OpenCV's cv2.resize(INTER_AREA) on uint8 RGB (shrinking, enlarging, integer and fractional ratios,
    one axis each way, one-pixel edges);
  - torchvision's bicubic antialiased resize on uint8 (what transformers' Qwen2-VL image processor and
    lerobot's torch geometry path call);
  - lerobot 0.6.1's own N1.7 eval transforms (_transform_n1_7_image_for_vlm_albumentations and
    _transform_n1_7_image_for_vlm_torch) on several frame sizes and settings;
  - transformers 5.5.4's Qwen2VLImageProcessor (torchvision backend) built with explicit arguments.

Frames are not stored: they come from `synth`, an integer-only pattern (gradients, checkerboard edges and
hashed noise) that the C++ tests rebuild bit for bit (tests/vision/test_gr00t_preprocess.cpp); `synth/check` pins a
small one so a drift in either copy shows up directly. The run is deterministic and byte-identical for the same
package versions.

Run in the oracle virtualenv:
    tools/oracle/run.sh gr00t_vision_fixtures.py [--out tests/fixtures/vision/gr00t]
"""

import argparse
import inspect
import json
import os
from importlib.metadata import version

import cv2
import numpy as np
import torch
import torchvision
from PIL import Image as PILImage
from safetensors.numpy import save_file
from torchvision.transforms import InterpolationMode
from torchvision.transforms.v2 import functional as tvF
from transformers import Qwen2VLImageProcessor
from transformers.models.qwen2_vl.image_processing_qwen2_vl import smart_resize

from lerobot.policies.groot.processor_groot import (
    _transform_n1_7_image_for_vlm_albumentations,
    _transform_n1_7_image_for_vlm_torch,
)

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# ---------------------------------------------------------------- frames


def synth(h, w, seed, kind="scene"):
    """uint8 HxWx3. 'scene': per-channel gradient (x, y, x+y) scaled by 3/4 plus 6 bits of hashed noise, inverted
    on a 16-pixel checkerboard. 'binary': every value 0 or 255 from one hash bit (many exact ties in averages).
    All arithmetic is uint32 with wrap-around, so C++ reproduces it exactly."""
    y, x, c = np.meshgrid(np.arange(h, dtype=np.uint32), np.arange(w, dtype=np.uint32),
                          np.arange(3, dtype=np.uint32), indexing="ij")
    with np.errstate(over="ignore"):
        i = (y * np.uint32(w) + x) * np.uint32(3) + c
        k = i * np.uint32(2654435761) + np.uint32(seed) * np.uint32(40503)
        k ^= k >> np.uint32(15)
        k *= np.uint32(2246822519)
        k ^= k >> np.uint32(13)
    if kind == "binary":
        return np.where((k >> np.uint32(20)) & np.uint32(1), 255, 0).astype(np.uint8)
    assert kind == "scene"
    gx = x * np.uint32(255) // np.uint32(max(w - 1, 1))
    gy = y * np.uint32(255) // np.uint32(max(h - 1, 1))
    gxy = (x + y) * np.uint32(255) // np.uint32(max(w + h - 2, 1))
    base = np.where(c == 0, gx, np.where(c == 1, gy, gxy))
    v = base * np.uint32(3) // np.uint32(4) + ((k >> np.uint32(24)) & np.uint32(63))
    v = np.where(((x >> np.uint32(4)) + (y >> np.uint32(4))) & np.uint32(1), np.uint32(255) - v, v)
    return v.astype(np.uint8)


def frame(spec):
    """spec: {"h", "w", "seed", "kind"}."""
    return synth(spec["h"], spec["w"], spec["seed"], spec.get("kind", "scene"))


def spec(h, w, seed, kind="scene"):
    return {"h": h, "w": w, "seed": seed, "kind": kind}


def chw(img):
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).contiguous()


def hwc(t):
    return np.ascontiguousarray(t.permute(1, 2, 0).numpy())


# ---------------------------------------------------------------- cases

# cv2.resize(INTER_AREA): (name, in_h, in_w, out_h, out_w, seed, kind)
AREA_CASES = [
    # integer shrink: the 2x2 fast path (with an odd row length for the SIMD tail), 3x3, 4x2, one axis only
    ("half_64x96", 64, 96, 32, 48, 1, "scene"),
    ("half_odd_50x86", 50, 86, 25, 43, 2, "scene"),
    ("half_binary_34x46", 34, 46, 17, 23, 3, "binary"),
    ("third_60x90", 60, 90, 20, 30, 4, "scene"),
    ("int_4x2_64x64", 64, 64, 16, 32, 5, "binary"),
    ("int_x_only_40x60", 40, 60, 40, 30, 6, "scene"),
    ("int_y_only_45x20", 45, 20, 9, 20, 7, "binary"),
    # fractional shrink
    ("frac_240x320_150x200", 240, 320, 150, 200, 8, "scene"),
    ("frac_100x75_37x29", 100, 75, 37, 29, 9, "scene"),
    ("frac_97x131_50x67", 97, 131, 50, 67, 10, "binary"),
    ("frac_37x53_11x7", 37, 53, 11, 7, 11, "scene"),
    ("frac_x_only_30x50_30x33", 30, 50, 30, 33, 12, "scene"),
    # one-pixel edges
    ("row_1x50_1x7", 1, 50, 1, 7, 14, "scene"),
    ("col_50x1_13x1", 50, 1, 13, 1, 15, "scene"),
    ("to_1x1_9x9", 9, 9, 1, 1, 16, "binary"),
    ("to_1x3_5x7", 5, 7, 1, 3, 17, "scene"),
    # enlarging (OpenCV emulates it with a bilinear rule and fixed-point weights). The pipeline's own sizes
    # (480x640 -> 256x341, 243x323 -> 256x340) are covered by geometry.safetensors.
    ("up_20x30_41x67", 20, 30, 41, 67, 18, "scene"),
    ("up_7x5_23x17", 7, 5, 23, 17, 19, "binary"),
    ("up_1x1_5x4", 1, 1, 5, 4, 20, "scene"),
    ("up_1x9_3x20", 1, 9, 3, 20, 21, "scene"),
    ("up_2x_16x24_32x48", 16, 24, 32, 48, 22, "scene"),
    ("up_30x23_128x96", 30, 23, 128, 96, 23, "scene"),
    ("up_y_only_20x30_47x30", 20, 30, 47, 30, 25, "scene"),
    # one axis shrinks, the other grows: both go through the bilinear rule
    ("mixed_40x30_20x60", 40, 30, 20, 60, 26, "scene"),
    ("mixed_30x40_45x20", 30, 40, 45, 20, 27, "binary"),
    ("mixed_near_one_129x173_128x174", 129, 173, 128, 174, 28, "scene"),
    ("same_10x12", 10, 12, 10, 12, 29, "scene"),
]

# torchvision resize(BICUBIC, antialias=True) on uint8: (name, in_h, in_w, out_h, out_w, seed, kind)
BICUBIC_CASES = [
    ("widen_40x50_40x64", 40, 50, 40, 64, 31, "scene"),
    ("down_97x131_50x67", 97, 131, 50, 67, 32, "scene"),
    ("down_binary_64x48_21x16", 64, 48, 21, 16, 33, "binary"),
    ("up_20x30_64x96", 20, 30, 64, 96, 34, "scene"),
    ("up_binary_9x7_40x33", 9, 7, 40, 33, 35, "binary"),
    ("mixed_40x30_20x60", 40, 30, 20, 60, 36, "scene"),
    ("h_only_50x40_77x40", 50, 40, 77, 40, 37, "scene"),
    ("w_only_30x90_30x41", 30, 90, 30, 41, 38, "scene"),
    # (a 1x1 output is left out: torch 2.11 trips an internal assert on it for uint8 input)
    ("to_1x3_5x6", 5, 6, 1, 3, 39, "scene"),
    ("to_4x1_9x5", 9, 5, 4, 1, 42, "binary"),
    ("from_1x1_4x3", 1, 1, 4, 3, 40, "scene"),
    ("big_shrink_300x400_37x29", 300, 400, 37, 29, 41, "binary"),
]

# Pillow's Image.resize(BICUBIC) on RGB (GR00T N1.6's Eagle fetch_image): the torchvision cases, plus the sizes the
# released N1.6 setting gives (shortest edge 256, crop 0.95, then smart_resize to multiples of 28).
PIL_BICUBIC_CASES = BICUBIC_CASES + [
    ("n16_256x341_252x336", 256, 341, 252, 336, 43, "scene"),
    ("n16_256x256_252x252", 256, 256, 252, 252, 44, "binary"),
    ("n16_256x455_252x448", 256, 455, 252, 448, 45, "scene"),
    ("to_1x1_7x9", 7, 9, 1, 1, 46, "scene"),
]

# lerobot's albumentations (cv2) eval transform. kwargs are passed through as lerobot's step passes them.
GEOMETRY_CASES = [
    # the released-checkpoint setting: shortest edge 256, crop fraction 0.95 (480x640 -> 256x340)
    ("e256_f095_480x640", spec(480, 640, 51), dict(image_crop_size=None, image_target_size=[256, 256],
                                                   shortest_image_edge=256, crop_fraction=0.95)),
    # lerobot's fallback geometry: target 256, crop 230 -> fraction 230/256, letter-boxed to a square first
    ("lerobot_default_letterbox_480x640", spec(480, 640, 52), dict(image_crop_size=[230, 230],
                                                                   image_target_size=[256, 256],
                                                                   shortest_image_edge=None, crop_fraction=None,
                                                                   letter_box_transform=True)),
    ("e256_f095_120x160", spec(120, 160, 53), dict(image_crop_size=None, image_target_size=[256, 256],
                                                   shortest_image_edge=256, crop_fraction=0.95)),
    ("e128_f095_letterbox_200x100", spec(200, 100, 54), dict(image_crop_size=None, image_target_size=[128, 128],
                                                             shortest_image_edge=128, crop_fraction=0.95,
                                                             letter_box_transform=True)),
    ("e96_crop_derived_200x100", spec(200, 100, 55, "binary"), dict(image_crop_size=[86, 86],
                                                                    image_target_size=[96, 96],
                                                                    shortest_image_edge=None, crop_fraction=None)),
    ("already_e_128x128_f095", spec(128, 128, 56), dict(image_crop_size=None, image_target_size=[128, 128],
                                                        shortest_image_edge=None, crop_fraction=0.95)),
    ("no_crop_f1_75x133", spec(75, 133, 57), dict(image_crop_size=None, image_target_size=[64, 64],
                                                  shortest_image_edge=None, crop_fraction=1.0)),
    ("no_crop_at_all_90x60", spec(90, 60, 58), dict(image_crop_size=None, image_target_size=[48, 48],
                                                    shortest_image_edge=None, crop_fraction=None)),
    ("edge_overrides_target_97x131", spec(97, 131, 59, "binary"), dict(image_crop_size=[40, 40],
                                                                       image_target_size=[50, 50],
                                                                       shortest_image_edge=72, crop_fraction=0.9)),
]

# lerobot's torch (torchvision bicubic) eval transform, the default when use_albumentations is false.
TORCH_GEOMETRY_CASES = [
    ("default_480x640", spec(480, 640, 61), dict(image_crop_size=[230, 230], image_target_size=[256, 256],
                                                 shortest_image_edge=None, crop_fraction=None)),
    ("letterbox_e256_f095_target128_120x160", spec(120, 160, 62), dict(image_crop_size=None,
                                                                       image_target_size=[128, 128],
                                                                       shortest_image_edge=256, crop_fraction=0.95,
                                                                       letter_box_transform=True)),
    ("non_square_target_200x100", spec(200, 100, 63, "binary"), dict(image_crop_size=[50, 50],
                                                                     image_target_size=[60, 80],
                                                                     shortest_image_edge=None, crop_fraction=None)),
    ("no_crop_64x64_to_64x64", spec(64, 64, 64), dict(image_crop_size=None, image_target_size=[64, 64],
                                                      shortest_image_edge=None, crop_fraction=None)),
]

# Qwen2-VL image processor. The "qwen3vl" settings are the Qwen3-VL preprocessor_config.json values;
# smaller settings keep full pixel_values small enough to store.
QWEN_SETTINGS = {
    "qwen3vl": dict(patch_size=16, temporal_patch_size=2, merge_size=2, image_mean=[0.5, 0.5, 0.5],
                    image_std=[0.5, 0.5, 0.5], size={"shortest_edge": 65536, "longest_edge": 16777216}, resample=3),
    "small_clip": dict(patch_size=16, temporal_patch_size=2, merge_size=2,
                       image_mean=[0.48145466, 0.4578275, 0.40821073], image_std=[0.26862954, 0.26130258, 0.27577711],
                       size={"shortest_edge": 4096, "longest_edge": 8192}, resample=3),
    "qwen2vl_p14": dict(patch_size=14, temporal_patch_size=2, merge_size=2, image_mean=[0.5, 0.5, 0.5],
                        image_std=[0.5, 0.5, 0.5], size={"shortest_edge": 784, "longest_edge": 12544}, resample=3),
}
# (name, settings, frame source, store full pixel_values). Source "geometry:<case>" uses that geometry output.
# Large cases store sampled rows plus every row's float64 sum; the e2e case also stores its resized uint8 image.
QWEN_CASES = [
    ("resize_256x340", "qwen3vl", "geometry:e256_f095_480x640", False),  # the e2e case: 256x340 -> 256x352
    ("noop_256x256", "qwen3vl", "geometry:lerobot_default_letterbox_480x640", False),
    ("upscale_300x200", "qwen3vl", spec(300, 200, 71), False),
    ("tiny_12x20_upscaled", "qwen3vl", spec(12, 20, 72), False),
    ("small_clip_50x70", "small_clip", spec(50, 70, 73), True),
    ("small_clip_up_20x30", "small_clip", spec(20, 30, 74, "binary"), True),
    ("small_clip_max_100x150", "small_clip", spec(100, 150, 75), True),
    ("p14_40x40", "qwen2vl_p14", spec(40, 40, 76), True),
    ("p14_61x90", "qwen2vl_p14", spec(61, 90, 77), True),
]
# Sizes smart_resize refuses: an aspect ratio above 200. (No frame is too small: transformers 5.5.4 scales any
# frame up to min_pixels, so every side ends at least patch_size * merge_size pixels long.)
QWEN_ERRORS = [
    ("aspect_2x403", "qwen3vl", 2, 403),
    ("aspect_403x2", "small_clip", 403, 2),
]
SAMPLED_ROWS = 12  # rows of pixel_values stored for the large cases: first, last, and evenly spaced


def sampled_rows(n):
    return sorted(set([0, n - 1] + [int(k * (n - 1) / (SAMPLED_ROWS - 1)) for k in range(SAMPLED_ROWS)]))


def save(tensors, out, name, meta):
    """All metadata goes under one key as sorted JSON so regeneration is byte-identical."""
    save_file(tensors, os.path.join(out, name), metadata={"fixture": json.dumps(meta, sort_keys=True)})


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(REPO, "tests", "fixtures", "vision", "gr00t"))
    args = ap.parse_args()
    out = args.out
    os.makedirs(out, exist_ok=True)
    torch.set_num_threads(1)
    cv2.setNumThreads(1)

    versions = {
        "opencv": cv2.__version__,
        "torch": torch.__version__,
        "torchvision": torchvision.__version__,
        "transformers": version("transformers"),
        "lerobot": version("lerobot"),
        "numpy": np.__version__,
        "safetensors": version("safetensors"),
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),
    }
    # The functions the C++ port follows; a changed signature means the fixtures no longer mean the same thing.
    signatures = {
        "_transform_n1_7_image_for_vlm_albumentations": str(inspect.signature(_transform_n1_7_image_for_vlm_albumentations)),
        "_transform_n1_7_image_for_vlm_torch": str(inspect.signature(_transform_n1_7_image_for_vlm_torch)),
    }

    # The C++ copy of `synth` is checked against this one directly.
    check = synth(7, 9, 3)
    check_binary = synth(5, 6, 4, "binary")

    # ---- cv2 INTER_AREA
    tensors, cases = {"synth/check": check, "synth/check_binary": check_binary}, []
    for name, h, w, oh, ow, seed, kind in AREA_CASES:
        img = synth(h, w, seed, kind)
        y = cv2.resize(img, (ow, oh), interpolation=cv2.INTER_AREA)
        assert y.shape == (oh, ow, 3), (name, y.shape)
        tensors[f"area/{name}"] = np.ascontiguousarray(y)
        cases.append({"name": name, "frame": spec(h, w, seed, kind), "out": [oh, ow]})
    save(tensors, out, "area.safetensors", {"versions": versions, "cases": cases})

    # ---- torchvision bicubic + antialias on uint8
    tensors, cases = {}, []
    for name, h, w, oh, ow, seed, kind in BICUBIC_CASES:
        img = synth(h, w, seed, kind)
        y = tvF.resize(chw(img), [oh, ow], interpolation=InterpolationMode.BICUBIC, antialias=True)
        assert y.dtype == torch.uint8
        tensors[f"bicubic/{name}"] = hwc(y)
        cases.append({"name": name, "frame": spec(h, w, seed, kind), "out": [oh, ow]})
    save(tensors, out, "bicubic.safetensors", {"versions": versions, "cases": cases})

    # ---- Pillow bicubic (GR00T N1.6's Eagle processor)
    tensors, cases = {}, []
    for name, h, w, oh, ow, seed, kind in PIL_BICUBIC_CASES:
        img = synth(h, w, seed, kind)
        y = np.asarray(PILImage.fromarray(img, "RGB").resize((ow, oh), PILImage.BICUBIC), dtype=np.uint8)
        assert y.shape == (oh, ow, 3), (name, y.shape)
        tensors[f"pil/{name}"] = np.ascontiguousarray(y)
        cases.append({"name": name, "frame": spec(h, w, seed, kind), "out": [oh, ow]})
    save(tensors, out, "pil_bicubic.safetensors", {"versions": {**versions, "pillow": version("pillow")},
                                                   "cases": cases})

    # ---- lerobot geometry, both paths
    tensors, cases, geometry_out = {}, [], {}
    for name, fspec, kwargs in GEOMETRY_CASES:
        y = _transform_n1_7_image_for_vlm_albumentations(frame(fspec), **kwargs)
        y = np.ascontiguousarray(y)
        assert y.dtype == np.uint8 and y.ndim == 3
        geometry_out[name] = y
        tensors[f"albumentations/{name}"] = y
        cases.append({"name": name, "path": "albumentations", "frame": fspec, "kwargs": kwargs,
                      "out": list(y.shape[:2])})
    for name, fspec, kwargs in TORCH_GEOMETRY_CASES:
        y = hwc(_transform_n1_7_image_for_vlm_torch(chw(frame(fspec)), **kwargs))
        tensors[f"torch/{name}"] = y
        cases.append({"name": name, "path": "torch", "frame": fspec, "kwargs": kwargs, "out": list(y.shape[:2])})
    save(tensors, out, "geometry.safetensors", {"versions": versions, "signatures": signatures, "cases": cases})

    # ---- Qwen2-VL image processor
    tensors, cases = {}, []
    processors = {k: Qwen2VLImageProcessor(**v) for k, v in QWEN_SETTINGS.items()}
    for k, p in processors.items():
        assert p.backend == "torchvision", (k, p.backend)
    for name, setting, source, full in QWEN_CASES:
        p = processors[setting]
        img = geometry_out[source.split(":", 1)[1]] if isinstance(source, str) else frame(source)
        enc = p(images=[img], return_tensors="pt")
        pv = enc["pixel_values"].numpy()
        grid = enc["image_grid_thw"].numpy()
        assert pv.dtype == np.float32 and grid.shape == (1, 3)
        s = QWEN_SETTINGS[setting]
        factor = s["patch_size"] * s["merge_size"]
        rh, rw = smart_resize(img.shape[0], img.shape[1], factor=factor, min_pixels=s["size"]["shortest_edge"],
                              max_pixels=s["size"]["longest_edge"])
        resized = hwc(tvF.resize(chw(img), [rh, rw], interpolation=InterpolationMode.BICUBIC, antialias=True))
        assert [int(grid[0, 1]) * s["patch_size"], int(grid[0, 2]) * s["patch_size"]] == [rh, rw]
        case = {"name": name, "setting": setting, "source": source, "resized": [rh, rw],
                "grid_thw": [int(v) for v in grid[0]], "rows": int(pv.shape[0]), "row_size": int(pv.shape[1])}
        if name == "resize_256x340":
            tensors[f"qwen/{name}/resized"] = resized
        if full:
            tensors[f"qwen/{name}/pixel_values"] = np.ascontiguousarray(pv)
        else:
            rows = sampled_rows(pv.shape[0])
            tensors[f"qwen/{name}/row_index"] = np.asarray(rows, dtype=np.int64)
            tensors[f"qwen/{name}/rows"] = np.ascontiguousarray(pv[rows])
            tensors[f"qwen/{name}/row_sums"] = pv.astype(np.float64).sum(axis=1)
        cases.append(case)
    errors = []
    for name, setting, h, w in QWEN_ERRORS:
        try:
            processors[setting](images=[synth(h, w, 0)], return_tensors="pt")
        except Exception as e:  # noqa: BLE001 - any refusal counts; its text is recorded
            errors.append({"name": name, "setting": setting, "in": [h, w],
                           "error": f"{type(e).__name__}: {str(e).splitlines()[0]}"})
        else:
            raise AssertionError(f"the processor accepted {name}")
    save(tensors, out, "qwen.safetensors", {"versions": versions, "settings": QWEN_SETTINGS, "cases": cases,
                                             "errors": errors, "processor_class": type(processors["qwen3vl"]).__name__})

    total = sum(os.path.getsize(os.path.join(out, n)) for n in os.listdir(out))
    print(f"wrote {out}: {total / 1e6:.2f} MB; versions {versions}")


if __name__ == "__main__":
    main()
