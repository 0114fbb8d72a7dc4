// GR00T N1.7 camera-frame preprocessing, bit-exact with lerobot 0.6.1 + transformers 5.5.4 on CPU
// (docs/design/gr00t.md section 2.2):
//
//   uint8 RGB frame
//     -> GR00T eval geometry (lerobot processor_groot.py): optional letter-box to a square, resize so the shorter
//        side is E, centre crop by a fraction, resize again; cv2 INTER_AREA ("albumentations" path, what released
//        checkpoints use) or torchvision bicubic (the torch path, lerobot's default otherwise)
//     -> Qwen2-VL image processor (transformers, torchvision backend): smart_resize to multiples of
//        patch * merge, bicubic antialiased resize on uint8, fused rescale + normalise in float32, the frame
//        repeated to temporal_patch_size frames, patchified in merge-block order
//     -> pixel rows [patches, 3 * T * P * P] for the Qwen3-VL vision tower, and the grid (t, h, w) in patches.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "core/json_util.h"
#include "vision/image.h"
#include "vision/preprocess.h"

namespace tether::vision {

// ---------------------------------------------------------------- torchvision bicubic resize

// torchvision.transforms.v2.functional.resize(img, [out_h, out_w], BICUBIC, antialias=True) on a uint8 image, as
// torch's CPU kernel computes it: separable (horizontal pass first, rounded back to uint8, then vertical), Keys
// cubic a = -0.5 stretched by the scale when shrinking, weights normalised in double and quantised to int16 at the
// largest precision that fits, each output rounded half up and clamped. Same size: returned unchanged.
Image resize_bicubic_antialias(const Image& img, int out_h, int out_w);

// Pillow's Image.resize((out_w, out_h), BICUBIC) on an RGB image: the same separable scheme with Pillow's own
// cubic formula and int32 weights at a fixed 22 bits. Same size: returned unchanged (Pillow copies).
Image resize_bicubic_pil(const Image& img, int out_h, int out_w);

// ---------------------------------------------------------------- GR00T geometry

// The image fields of an N1.7 checkpoint's processor_config.json ("processor_kwargs").
struct Gr00tImageGeometry {
  int target_h = 256, target_w = 256;                              // image_target_size
  std::optional<std::array<int, 2>> crop_size = std::array{230, 230};  // image_crop_size
  std::optional<int> shortest_edge;                                // shortest_image_edge; unset: target_h
  std::optional<double> crop_fraction;                             // unset: crop_size[0] / target_h
  bool use_albumentations = false;                                 // cv2 INTER_AREA path; else torchvision bicubic
  bool letter_box = false;                                         // letter_box_transform

  int resize_edge() const { return shortest_edge.value_or(target_h); }
  // The centre-crop fraction to apply, or nullopt when nothing is cropped (no fraction configured, or exactly 1).
  // Throws invalid_argument outside (0, 1]; lerobot silently skips such a crop, Tether refuses the setting.
  std::optional<double> effective_crop_fraction() const;

  // lerobot's reading of processor_kwargs: when image_target_size is absent, the N1.7 defaults apply (target 256,
  // crop 230) and shortest_image_edge / crop_fraction are ignored; non-boolean flags count as false.
  static Gr00tImageGeometry from_processor_kwargs(const Json& kwargs, const std::string& where);
  // Isaac-GR00T's N1.6 reading: E = shortest_image_edge, else image_target_size[0]; f = crop_fraction, else
  // image_crop_size[0] / image_target_size[0]; only the albumentations path (use_albumentations true) is supported.
  static Gr00tImageGeometry from_n16_processor_kwargs(const Json& kwargs, const std::string& where);
};

// Pads to a square with black, the top / left getting half the padding (rounded down). Square images are copied.
Image letter_box(const Image& img);

// The size after resizing the shorter side to `edge`: each side max(1, round(side * edge / shorter)), Python's
// round (half to even) on the double product. Equal to the input when the shorter side already is `edge`.
ResizedSize shortest_edge_size(int h, int w, int edge);

// The window [top, top + crop_h) x [left, left + crop_w) with top = (h - crop_h) / 2, left = (w - crop_w) / 2.
Image center_crop(const Image& img, int crop_h, int crop_w);

// lerobot _transform_n1_7_image_for_vlm_albumentations (eval): letter-box?, shorter side -> E with cv2
// INTER_AREA, centre crop of max(1, int(side * f)) pixels per side (truncated), shorter side -> E again.
// The aspect ratio is kept: 480x640 with E = 256, f = 0.95 gives 256x340.
Image gr00t_geometry_albumentations(const Image& frame, const Gr00tImageGeometry& g);

// lerobot _transform_n1_7_image_for_vlm_torch: letter-box?, resize to E x E (bicubic, antialias), centre crop of
// max(1, round(E * f)) pixels per side, resize to target_h x target_w (bicubic, antialias) unless already there.
Image gr00t_geometry_torch(const Image& frame, const Gr00tImageGeometry& g);

// The path the checkpoint selects (use_albumentations).
Image gr00t_geometry(const Image& frame, const Gr00tImageGeometry& g);

// ---------------------------------------------------------------- Qwen2-VL image processor

// The backbone repository's preprocessor_config.json. Defaults are Qwen3-VL's.
struct QwenImageConfig {
  int patch_size = 16, temporal_patch_size = 2, merge_size = 2;
  int64_t min_pixels = 65536, max_pixels = 16777216;  // size.shortest_edge / size.longest_edge
  std::array<double, 3> image_mean{0.5, 0.5, 0.5}, image_std{0.5, 0.5, 0.5};
  double rescale_factor = 1.0 / 255.0;
  bool do_resize = true, do_rescale = true, do_normalize = true;

  int factor() const { return patch_size * merge_size; }
  int64_t row_size() const { return int64_t(3) * temporal_patch_size * patch_size * patch_size; }

  // Reads the fields transformers' Qwen2VLImageProcessor takes; top-level min_pixels / max_pixels override `size`
  // as its constructor does. Refuses a resample other than bicubic (3), a zero std and non-positive sizes.
  static QwenImageConfig from_json(const Json& j, const std::string& where);
};

// transformers smart_resize(h, w, factor = patch * merge, min_pixels, max_pixels): both sides multiples of the
// factor, the area brought within [min_pixels, max_pixels] keeping the aspect ratio (a frame of any size is
// scaled up to min_pixels, so no side ends below the factor). Throws invalid_argument when the aspect ratio
// exceeds 200, as upstream does.
ResizedSize qwen_smart_resize(int h, int w, const QwenImageConfig& cfg);

// A frame's patch grid: t temporal, h x w spatial patches (pixel rows = t * h * w).
struct PatchGrid {
  int64_t t = 1, h = 0, w = 0;
  int64_t patches() const { return t * h * w; }
};

struct PixelPatches {
  PatchGrid grid;
  int64_t row_size = 0;       // 3 * temporal_patch_size * patch_size^2
  std::vector<float> values;  // grid.patches() rows of row_size
};

// Normalises an image whose sides are multiples of patch * merge and writes its pixel rows into `out`
// (grid.patches() * row_size floats): rows in merge-block order (block row, block column, row in block, column in
// block), each row's values in (channel, temporal copy, y, x) order, the one frame repeated temporal_patch_size
// times. Values are (x - m) / s in float32 with m = float(mean) * float(1 / rescale_factor) (likewise s), the
// fused form transformers uses.
PatchGrid qwen_patchify(const Image& img, const QwenImageConfig& cfg, float* out);

// The whole Qwen2VLImageProcessor call for one image: smart_resize, bicubic resize (skipped when the size is
// unchanged), then qwen_patchify.
PixelPatches qwen_image_process(const Image& img, const QwenImageConfig& cfg);

// ---------------------------------------------------------------- one camera frame, end to end

// GR00T geometry then the Qwen2-VL processor: what lerobot feeds the N1.7 backbone for one frame.
PixelPatches gr00t_preprocess_frame(const Image& frame, const Gr00tImageGeometry& geometry,
                                    const QwenImageConfig& qwen);

// ---------------------------------------------------------------- GR00T N1.6 (Eagle processor)

// The Eagle processor's smart_resize (factor 28, 4 * 28^2 to 4096 * 28^2 pixels): Python-rounded multiples of 28
// clamped to [28, 7000]; too many pixels: scaled down from that rounded size and floored; too few: scaled up from
// the original size and rounded up. Throws invalid_argument past an aspect ratio of 200.
ResizedSize eagle_smart_resize(int h, int w);

struct EagleFrame {
  Image image;                // after the geometry, smart_resize and Pillow's bicubic resize
  std::vector<float> pixels;  // [3, H, W]: (x - 127.5) / 127.5 in float32 (transformers' fused rescale + normalise)
};

// What Isaac-GR00T's N1.6 processor feeds the SigLIP2 tower for one camera frame: the albumentations eval geometry,
// the Eagle fetch_image (smart_resize + Pillow bicubic) and the image processor's normalisation.
EagleFrame eagle_preprocess_frame(const Image& frame, const Gr00tImageGeometry& geometry);

// The Eagle processor's part alone (fetch_image and the image processor), for a frame already through the geometry.
EagleFrame eagle_process_image(const Image& shaped);

}  // namespace tether::vision
