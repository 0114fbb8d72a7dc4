// GR00T N1.7 frame preprocessing: lerobot's eval geometry, torchvision's uint8 bicubic resize and the Qwen2-VL image
// processor, restated from lerobot 0.6.1 (policies/groot/processor_groot.py), torch 2.11
// (aten/src/ATen/native/cpu/UpSampleKernel.cpp, UpSampleKernelAVXAntialias.h), torchvision 0.26 and
// transformers 5.5.4 (models/qwen2_vl/image_processing_qwen2_vl.py, image_processing_backends.py).
#include "vision/gr00t_preprocess.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>

#include "core/error.h"
#include "vision/area_resize.h"

namespace tether::vision {

namespace {

void check_image(const Image& img, const char* what) {
  if (img.height <= 0 || img.width <= 0)
    throw Error(ErrorCode::invalid_argument, std::string(what) + ": empty image (" + std::to_string(img.height) +
                                                 "x" + std::to_string(img.width) + ")");
  if (img.rgb.size() != size_t(img.height) * img.width * 3)
    throw Error(ErrorCode::invalid_argument, std::string(what) + ": pixel buffer does not match " +
                                                 std::to_string(img.height) + "x" + std::to_string(img.width) + "x3");
}

Image blank(int h, int w) {
  Image out;
  out.height = h;
  out.width = w;
  out.rgb.assign(size_t(h) * w * 3, 0);
  return out;
}

// Python's round() on a double: nearest, ties to even (the default rounding mode).
inline int64_t py_round(double v) { return int64_t(std::nearbyint(v)); }

// ---------------------------------------------------------------- bicubic antialias weights

// Keys' cubic with a = -0.5 (PIL's choice, which torch follows when antialiasing), in the fused multiply-add form a
// contracting compiler gives torch's kernel. The unfused form yields the same int16 weights for every size pair up
// to 400 x 400 (checked), so either matches torch in practice.
double keys_cubic(double x) {
  x = std::abs(x);
  if (x < 1.0) return std::fma(std::fma(1.5, x, -2.5) * x, x, 1.0);
  if (x < 2.0) return std::fma(std::fma(std::fma(-0.5, x, 2.5), x, -4.0), x, 2.0);
  return 0.0;
}

// Per output index along one axis: the first source index, how many follow, and int16 weights with a shared
// precision (torch's _compute_index_ranges_int16_weights).
struct AaAxis {
  int taps = 0;
  unsigned precision = 0;
  std::vector<int> start, count;
  std::vector<int32_t> w;  // out * taps (int16 range for torch's kernel)
};

AaAxis bicubic_aa_axis(int in, int out) {
  AaAxis a;
  const double scale = double(in) / double(out);
  // The filter's support widens with the scale when shrinking: that is the antialiasing.
  const double support = scale >= 1.0 ? 2.0 * scale : 2.0;
  const double invscale = scale >= 1.0 ? 1.0 / scale : 1.0;
  a.taps = int(std::ceil(support)) * 2 + 1;
  a.start.resize(out);
  a.count.resize(out);
  std::vector<double> wd(size_t(out) * a.taps, 0.0);
  double wt_max = 0.0;
  for (int i = 0; i < out; ++i) {
    const double center = scale * (i + 0.5);
    const int64_t xmin = std::max(int64_t(center - support + 0.5), int64_t(0));
    int64_t xsize = std::min(int64_t(center + support + 0.5), int64_t(in)) - xmin;
    xsize = std::clamp(xsize, int64_t(0), int64_t(a.taps));
    double* w = wd.data() + size_t(i) * a.taps;
    double total = 0.0;
    for (int64_t j = 0; j < xsize; ++j) {
      w[j] = keys_cubic((double(j + xmin) - center + 0.5) * invscale);
      total += w[j];
    }
    if (total != 0.0) {
      for (int64_t j = 0; j < xsize; ++j) {
        w[j] /= total;
        wt_max = std::max(wt_max, w[j]);
      }
    }
    a.start[i] = int(xmin);
    a.count[i] = int(xsize);
  }
  // The largest precision whose biggest weight still fits in 15 bits.
  unsigned p = 0;
  for (; p < 22; ++p) {
    if (int(0.5 + wt_max * double(1 << (p + 1))) >= (1 << 15)) break;
  }
  a.precision = p;
  a.w.resize(wd.size());
  for (size_t k = 0; k < wd.size(); ++k) {
    const double v = wd[k] * double(1 << p);
    a.w[k] = int16_t(v < 0 ? int(-0.5 + v) : int(0.5 + v));
  }
  return a;
}

// Pillow's bicubic filter (a = -0.5) in its own operation order (Resample.c bicubic_filter).
double pil_bicubic(double x) {
  constexpr double a = -0.5;
  if (x < 0.0) x = -x;
  if (x < 1.0) return ((a + 2.0) * x - (a + 3.0)) * x * x + 1;
  if (x < 2.0) return (((x - 5) * x + 8) * x - 4) * a;
  return 0.0;
}

// Pillow's precompute_coeffs + normalize_coeffs_8bpc: the same support rule as torch's, weights normalised in
// double and quantised to int32 at a fixed 22 bits (PRECISION_BITS = 32 - 8 - 2).
AaAxis pil_bicubic_axis(int in, int out) {
  AaAxis a;
  const double scale = double(in) / double(out);
  const double filterscale = std::max(scale, 1.0);
  const double support = 2.0 * filterscale;
  a.taps = int(std::ceil(support)) * 2 + 1;
  a.precision = 22;
  a.start.resize(out);
  a.count.resize(out);
  a.w.assign(size_t(out) * a.taps, 0);
  std::vector<double> k(size_t(a.taps));
  for (int xx = 0; xx < out; ++xx) {
    const double center = (xx + 0.5) * scale;
    const double ss = 1.0 / filterscale;
    const int xmin = std::max(int(center - support + 0.5), 0);
    const int xmax = std::min(int(center + support + 0.5), in) - xmin;
    double ww = 0.0;
    for (int x = 0; x < xmax; ++x) {
      k[size_t(x)] = pil_bicubic((x + xmin - center + 0.5) * ss);
      ww += k[size_t(x)];
    }
    for (int x = 0; x < xmax; ++x) {
      const double v = (ww != 0.0 ? k[size_t(x)] / ww : k[size_t(x)]) * double(1 << 22);
      a.w[size_t(xx) * a.taps + x] = v < 0 ? int32_t(-0.5 + v) : int32_t(0.5 + v);
    }
    a.start[xx] = xmin;
    a.count[xx] = xmax;
  }
  return a;
}

// One output sample of a separable pass: the source samples p[k * step], k in [start, start + count), weighted in
// fixed point, rounded half up and clamped to uint8 (torch rounds each pass, so the vertical pass reads uint8).
inline uint8_t aa_sample(const uint8_t* p, int64_t step, const AaAxis& a, int i) {
  const int32_t* w = a.w.data() + size_t(i) * a.taps;
  int32_t acc = int32_t(1) << (a.precision - 1);  // the +0.5 of round half up
  for (int j = 0; j < a.count[i]; ++j) acc += int32_t(p[int64_t(a.start[i] + j) * step]) * w[j];
  return uint8_t(std::clamp(acc >> a.precision, 0, 255));
}

Image resize_horizontal(const Image& img, int out_w, bool pil) {
  const AaAxis a = pil ? pil_bicubic_axis(img.width, out_w) : bicubic_aa_axis(img.width, out_w);
  Image out = blank(img.height, out_w);
  for (int y = 0; y < img.height; ++y) {
    const uint8_t* row = img.rgb.data() + int64_t(y) * img.width * 3;
    uint8_t* o = out.rgb.data() + int64_t(y) * out_w * 3;
    for (int x = 0; x < out_w; ++x)
      for (int c = 0; c < 3; ++c) o[x * 3 + c] = aa_sample(row + c, 3, a, x);
  }
  return out;
}

Image resize_vertical(const Image& img, int out_h, bool pil) {
  const AaAxis a = pil ? pil_bicubic_axis(img.height, out_h) : bicubic_aa_axis(img.height, out_h);
  Image out = blank(out_h, img.width);
  const int64_t stride = int64_t(img.width) * 3;
  for (int y = 0; y < out_h; ++y) {
    uint8_t* o = out.rgb.data() + int64_t(y) * stride;
    for (int64_t k = 0; k < stride; ++k) o[k] = aa_sample(img.rgb.data() + k, stride, a, y);
  }
  return out;
}

// ---------------------------------------------------------------- GR00T geometry helpers

// The shorter-side resize lerobot applies twice (cv2 INTER_AREA), skipped when the shorter side already is `edge`.
Image resize_shorter_side_area(const Image& img, int edge) {
  if (std::min(img.height, img.width) == edge) return img;
  const ResizedSize s = shortest_edge_size(img.height, img.width, edge);
  return resize_area(img, s.height, s.width);
}

void check_geometry(const Gr00tImageGeometry& g) {
  if (g.target_h <= 0 || g.target_w <= 0)
    throw Error(ErrorCode::invalid_argument, "GR00T image geometry: image_target_size must be positive, got " +
                                                 std::to_string(g.target_h) + "x" + std::to_string(g.target_w));
  if (g.resize_edge() <= 0)
    throw Error(ErrorCode::invalid_argument,
                "GR00T image geometry: shortest_image_edge must be positive, got " + std::to_string(g.resize_edge()));
}

// ---------------------------------------------------------------- Qwen normalisation

// Per channel, the float32 value of every uint8 level, computed the way transformers does: with rescale and
// normalise both on, mean and std are float32 tensors multiplied by 1 / rescale_factor (float32 arithmetic), and
// the uint8 image, cast to float32, is shifted and divided (two separate float32 operations).
struct LevelTable {
  float v[3][256];
};

LevelTable level_table(const QwenImageConfig& cfg) {
  LevelTable t{};
  const float inv_rescale = float(1.0 / cfg.rescale_factor);
  for (int c = 0; c < 3; ++c) {
    float mean = float(cfg.image_mean[c]), std = float(cfg.image_std[c]);
    if (cfg.do_rescale && cfg.do_normalize) {
      mean = mean * inv_rescale;
      std = std * inv_rescale;
    }
    for (int x = 0; x < 256; ++x) {
      const float f = float(x);
      if (cfg.do_normalize) {
        t.v[c][x] = (f - mean) / std;
      } else if (cfg.do_rescale) {
        t.v[c][x] = f * float(cfg.rescale_factor);
      } else {
        t.v[c][x] = f;
      }
    }
  }
  return t;
}

int json_int(const Json& v, const std::string& key, const std::string& where) {
  if (!v.is_number()) throw Error(ErrorCode::format, where + ": field '" + key + "' is not a number (" + v.dump() + ")");
  return v.is_number_integer() ? v.get<int>() : int(v.get<double>());  // Python int() truncates
}

std::array<double, 3> json_triple(const Json& j, const std::string& key, std::array<double, 3> fallback,
                                  const std::string& where) {
  auto it = j.find(key);
  if (it == j.end() || it->is_null()) return fallback;
  if (it->is_number()) {
    const double v = it->get<double>();
    return {v, v, v};
  }
  if (!it->is_array() || it->size() != 3)
    throw Error(ErrorCode::format, where + ": field '" + key + "' must be a number or 3 numbers (" + it->dump() + ")");
  std::array<double, 3> out{};
  for (int c = 0; c < 3; ++c) {
    if (!(*it)[c].is_number()) throw Error(ErrorCode::format, where + ": field '" + key + "' has a non-number");
    out[c] = (*it)[c].get<double>();
  }
  return out;
}

// Both smart_resize variants refuse an empty frame and an aspect ratio past 200, as upstream does.
void check_smart_resize_input(int h, int w) {
  if (h <= 0 || w <= 0)
    throw Error(ErrorCode::invalid_argument,
                "smart_resize: empty image (" + std::to_string(h) + "x" + std::to_string(w) + ")");
  const double ratio = double(std::max(h, w)) / double(std::min(h, w));
  if (ratio > 200)
    throw Error(ErrorCode::invalid_argument, "smart_resize: absolute aspect ratio must be smaller than 200, got " +
                                                 std::to_string(ratio) + " (" + std::to_string(h) + "x" +
                                                 std::to_string(w) + ")");
}

// processor_kwargs readers as lerobot / Isaac-GR00T read them: a 2-element list (anything else counts as absent),
// and a flag (a non-boolean counts as false).
std::optional<std::array<int, 2>> kwargs_pair(const Json& kwargs, const char* key, const std::string& where) {
  auto it = kwargs.find(key);
  if (it == kwargs.end() || !it->is_array() || it->size() != 2) return std::nullopt;
  return std::array{json_int((*it)[0], key, where), json_int((*it)[1], key, where)};
}

bool kwargs_flag(const Json& kwargs, const char* key) {
  auto it = kwargs.find(key);
  return it != kwargs.end() && it->is_boolean() && it->get<bool>();
}

}  // namespace

// ---------------------------------------------------------------- public: resize

Image resize_bicubic_antialias(const Image& img, int out_h, int out_w) {
  check_image(img, "resize_bicubic_antialias");
  if (out_h <= 0 || out_w <= 0)
    throw Error(ErrorCode::invalid_argument, "resize_bicubic_antialias: empty output size " +
                                                 std::to_string(out_h) + "x" + std::to_string(out_w));
  if (out_h == img.height && out_w == img.width) return img;
  // torch runs the width pass first and rounds it to uint8 before the height pass.
  const Image widened = out_w != img.width ? resize_horizontal(img, out_w, false) : img;
  return out_h != img.height ? resize_vertical(widened, out_h, false) : widened;
}

Image resize_bicubic_pil(const Image& img, int out_h, int out_w) {
  check_image(img, "resize_bicubic_pil");
  if (out_h <= 0 || out_w <= 0)
    throw Error(ErrorCode::invalid_argument, "resize_bicubic_pil: empty output size " + std::to_string(out_h) + "x" +
                                                 std::to_string(out_w));
  if (out_h == img.height && out_w == img.width) return img;  // Image.resize to the same size is a copy
  // Pillow's ImagingResampleInner: the horizontal pass first, rounded to uint8, then the vertical one.
  const Image widened = out_w != img.width ? resize_horizontal(img, out_w, true) : img;
  return out_h != img.height ? resize_vertical(widened, out_h, true) : widened;
}

// ---------------------------------------------------------------- public: GR00T geometry

std::optional<double> Gr00tImageGeometry::effective_crop_fraction() const {
  std::optional<double> f = crop_fraction;
  if (!f && crop_size) f = double((*crop_size)[0]) / double(target_h);
  if (!f) return std::nullopt;
  if (!(*f > 0.0 && *f <= 1.0))
    throw Error(ErrorCode::invalid_argument,
                "GR00T image geometry: crop fraction " + std::to_string(*f) + " is outside (0, 1]" +
                    (crop_fraction ? "" : " (image_crop_size[0] / image_target_size[0])"));
  if (*f == 1.0) return std::nullopt;
  return f;
}

Gr00tImageGeometry Gr00tImageGeometry::from_processor_kwargs(const Json& kwargs, const std::string& where) {
  Gr00tImageGeometry g;
  if (!kwargs.is_object()) throw Error(ErrorCode::format, where + ": processor_kwargs is not an object");
  auto pair = [&](const char* key) { return kwargs_pair(kwargs, key, where); };
  auto flag = [&](const char* key) { return kwargs_flag(kwargs, key); };
  g.use_albumentations = flag("use_albumentations");
  g.letter_box = flag("letter_box_transform");
  const auto target = pair("image_target_size");
  if (!target) return g;  // N1.7 defaults: target 256, crop 230, no edge, no fraction
  g.target_h = (*target)[0];
  g.target_w = (*target)[1];
  g.crop_size = pair("image_crop_size");
  if (auto it = kwargs.find("shortest_image_edge"); it != kwargs.end() && !it->is_null())
    g.shortest_edge = json_int(*it, "shortest_image_edge", where);
  if (auto it = kwargs.find("crop_fraction"); it != kwargs.end() && !it->is_null()) {
    if (!it->is_number()) throw Error(ErrorCode::format, where + ": field 'crop_fraction' is not a number");
    g.crop_fraction = it->get<double>();
  }
  // Python treats 0 as unset for shortest_image_edge (`shortest_image_edge or target_h`).
  if (g.shortest_edge && *g.shortest_edge == 0) g.shortest_edge.reset();
  check_geometry(g);
  g.effective_crop_fraction();  // validate now rather than on the first frame
  return g;
}

Image letter_box(const Image& img) {
  check_image(img, "letter_box");
  if (img.height == img.width) return img;
  const int edge = std::max(img.height, img.width);
  const int top = (edge - img.height) / 2, left = (edge - img.width) / 2;
  Image out = blank(edge, edge);
  for (int y = 0; y < img.height; ++y)
    std::memcpy(out.rgb.data() + (int64_t(y + top) * edge + left) * 3, img.rgb.data() + int64_t(y) * img.width * 3,
                size_t(img.width) * 3);
  return out;
}

ResizedSize shortest_edge_size(int h, int w, int edge) {
  if (h <= 0 || w <= 0 || edge <= 0)
    throw Error(ErrorCode::invalid_argument, "shortest_edge_size: sizes must be positive");
  const int shorter = std::min(h, w);
  if (shorter == edge) return {h, w};
  const double scale = double(edge) / double(shorter);
  return {int(std::max<int64_t>(1, py_round(h * scale))), int(std::max<int64_t>(1, py_round(w * scale)))};
}

Image center_crop(const Image& img, int crop_h, int crop_w) {
  check_image(img, "center_crop");
  if (crop_h <= 0 || crop_w <= 0 || crop_h > img.height || crop_w > img.width)
    throw Error(ErrorCode::invalid_argument, "center_crop: " + std::to_string(crop_h) + "x" + std::to_string(crop_w) +
                                                 " does not fit in " + std::to_string(img.height) + "x" +
                                                 std::to_string(img.width));
  const int top = (img.height - crop_h) / 2, left = (img.width - crop_w) / 2;
  Image out = blank(crop_h, crop_w);
  for (int y = 0; y < crop_h; ++y)
    std::memcpy(out.rgb.data() + int64_t(y) * crop_w * 3,
                img.rgb.data() + (int64_t(y + top) * img.width + left) * 3, size_t(crop_w) * 3);
  return out;
}

Image gr00t_geometry_albumentations(const Image& frame, const Gr00tImageGeometry& g) {
  check_image(frame, "GR00T geometry");
  check_geometry(g);
  const std::optional<double> f = g.effective_crop_fraction();
  const int edge = g.resize_edge();
  Image img = resize_shorter_side_area(g.letter_box ? letter_box(frame) : frame, edge);
  if (f) {
    // Truncated crop sizes (int(h * f)), floored offsets.
    const int crop_h = std::max(1, int(img.height * *f));
    const int crop_w = std::max(1, int(img.width * *f));
    img = center_crop(img, crop_h, crop_w);
  }
  return resize_shorter_side_area(img, edge);
}

Image gr00t_geometry_torch(const Image& frame, const Gr00tImageGeometry& g) {
  check_image(frame, "GR00T geometry");
  check_geometry(g);
  const std::optional<double> f = g.effective_crop_fraction();
  const int edge = g.resize_edge();
  // The torch path squashes to a square: the aspect ratio is not kept.
  Image img = resize_bicubic_antialias(g.letter_box ? letter_box(frame) : frame, edge, edge);
  if (f) {
    // Rounded crop sizes (round(E * f), half to even), floored offsets.
    const int crop_h = int(std::max<int64_t>(1, py_round(img.height * *f)));
    const int crop_w = int(std::max<int64_t>(1, py_round(img.width * *f)));
    img = center_crop(img, crop_h, crop_w);
  }
  return resize_bicubic_antialias(img, g.target_h, g.target_w);
}

Image gr00t_geometry(const Image& frame, const Gr00tImageGeometry& g) {
  return g.use_albumentations ? gr00t_geometry_albumentations(frame, g) : gr00t_geometry_torch(frame, g);
}

// ---------------------------------------------------------------- public: Qwen2-VL image processor

QwenImageConfig QwenImageConfig::from_json(const Json& j, const std::string& where) {
  QwenImageConfig c;
  if (!j.is_object()) throw Error(ErrorCode::format, where + ": not a JSON object");
  c.patch_size = json_get_or<int>(j, "patch_size", c.patch_size, where);
  c.temporal_patch_size = json_get_or<int>(j, "temporal_patch_size", c.temporal_patch_size, where);
  c.merge_size = json_get_or<int>(j, "merge_size", c.merge_size, where);
  if (auto it = j.find("size"); it != j.end() && !it->is_null()) {
    if (!it->is_object()) throw Error(ErrorCode::format, where + ": field 'size' is not an object");
    c.min_pixels = json_get_or<int64_t>(*it, "shortest_edge", c.min_pixels, where + ": size");
    c.max_pixels = json_get_or<int64_t>(*it, "longest_edge", c.max_pixels, where + ": size");
  }
  c.min_pixels = json_get_or<int64_t>(j, "min_pixels", c.min_pixels, where);
  c.max_pixels = json_get_or<int64_t>(j, "max_pixels", c.max_pixels, where);
  c.image_mean = json_triple(j, "image_mean", c.image_mean, where);
  c.image_std = json_triple(j, "image_std", c.image_std, where);
  c.rescale_factor = json_get_or<double>(j, "rescale_factor", c.rescale_factor, where);
  c.do_resize = json_get_or<bool>(j, "do_resize", c.do_resize, where);
  c.do_rescale = json_get_or<bool>(j, "do_rescale", c.do_rescale, where);
  c.do_normalize = json_get_or<bool>(j, "do_normalize", c.do_normalize, where);
  if (const int resample = json_get_or<int>(j, "resample", 3, where); resample != 3)
    throw Error(ErrorCode::unsupported, where + ": resample " + std::to_string(resample) +
                                           " (only bicubic, 3, is implemented)");
  if (c.patch_size <= 0 || c.temporal_patch_size <= 0 || c.merge_size <= 0)
    throw Error(ErrorCode::format, where + ": patch_size, temporal_patch_size and merge_size must be positive");
  if (c.min_pixels <= 0 || c.max_pixels <= 0)
    throw Error(ErrorCode::format, where + ": size.shortest_edge and size.longest_edge must be positive");
  if (c.do_rescale && !(c.rescale_factor > 0.0))
    throw Error(ErrorCode::format, where + ": rescale_factor must be positive");
  if (c.do_normalize)
    for (double s : c.image_std)
      if (s == 0.0) throw Error(ErrorCode::format, where + ": image_std has a zero (division by zero upstream too)");
  return c;
}

ResizedSize qwen_smart_resize(int h, int w, const QwenImageConfig& cfg) {
  check_smart_resize_input(h, w);
  const int64_t factor = cfg.factor();
  int64_t hb = py_round(double(h) / double(factor)) * factor;
  int64_t wb = py_round(double(w) / double(factor)) * factor;
  const double area = double(int64_t(h) * w);
  if (hb * wb > cfg.max_pixels) {
    const double beta = std::sqrt(area / double(cfg.max_pixels));
    hb = std::max(factor, int64_t(std::floor(double(h) / beta / double(factor))) * factor);
    wb = std::max(factor, int64_t(std::floor(double(w) / beta / double(factor))) * factor);
  } else if (hb * wb < cfg.min_pixels) {
    const double beta = std::sqrt(double(cfg.min_pixels) / area);
    hb = int64_t(std::ceil(double(h) * beta / double(factor))) * factor;
    wb = int64_t(std::ceil(double(w) * beta / double(factor))) * factor;
  }
  return {int(hb), int(wb)};
}

PatchGrid qwen_patchify(const Image& img, const QwenImageConfig& cfg, float* out) {
  check_image(img, "qwen_patchify");
  const int P = cfg.patch_size, M = cfg.merge_size, T = cfg.temporal_patch_size;
  if (img.height % (P * M) != 0 || img.width % (P * M) != 0)
    throw Error(ErrorCode::invalid_argument, "qwen_patchify: " + std::to_string(img.height) + "x" +
                                                 std::to_string(img.width) + " is not a multiple of patch * merge = " +
                                                 std::to_string(P * M));
  const LevelTable lut = level_table(cfg);
  PatchGrid grid{1, img.height / P, img.width / P};
  const int64_t row = cfg.row_size();
  const int64_t plane = int64_t(P) * P;  // one channel of one temporal copy
  float* o = out;
  for (int64_t bh = 0; bh < grid.h / M; ++bh)
    for (int64_t bw = 0; bw < grid.w / M; ++bw)
      for (int mh = 0; mh < M; ++mh)
        for (int mw = 0; mw < M; ++mw, o += row) {
          const int64_t y0 = (bh * M + mh) * P, x0 = (bw * M + mw) * P;
          for (int c = 0; c < 3; ++c) {
            float* first = o + int64_t(c) * T * plane;
            for (int py = 0; py < P; ++py) {
              const uint8_t* src = img.rgb.data() + ((y0 + py) * img.width + x0) * 3 + c;
              for (int px = 0; px < P; ++px) first[py * P + px] = lut.v[c][src[px * 3]];
            }
            // A still frame is repeated to fill the temporal patch.
            for (int t = 1; t < T; ++t) std::memcpy(first + t * plane, first, size_t(plane) * sizeof(float));
          }
        }
  return grid;
}

PixelPatches qwen_image_process(const Image& img, const QwenImageConfig& cfg) {
  check_image(img, "Qwen2-VL image processor");
  PixelPatches out;
  out.row_size = cfg.row_size();
  auto patchify = [&](const Image& im) {
    out.values.resize(size_t(im.height / cfg.patch_size) * (im.width / cfg.patch_size) * out.row_size);
    out.grid = qwen_patchify(im, cfg, out.values.data());
  };
  if (!cfg.do_resize) {
    patchify(img);
    return out;
  }
  const ResizedSize s = qwen_smart_resize(img.height, img.width, cfg);
  if (s.height == img.height && s.width == img.width) {
    patchify(img);
  } else {
    patchify(resize_bicubic_antialias(img, s.height, s.width));
  }
  return out;
}

PixelPatches gr00t_preprocess_frame(const Image& frame, const Gr00tImageGeometry& geometry,
                                    const QwenImageConfig& qwen) {
  return qwen_image_process(gr00t_geometry(frame, geometry), qwen);
}

}  // namespace tether::vision

// ---------------------------------------------------------------- GR00T N1.6 (Eagle)

namespace tether::vision {

Gr00tImageGeometry Gr00tImageGeometry::from_n16_processor_kwargs(const Json& kwargs, const std::string& where) {
  if (!kwargs.is_object()) throw Error(ErrorCode::format, where + ": processor_kwargs is not an object");
  auto pair = [&](const char* key) { return kwargs_pair(kwargs, key, where); };
  auto flag = [&](const char* key) { return kwargs_flag(kwargs, key); };
  if (!flag("use_albumentations"))
    throw Error(ErrorCode::unsupported, where + ": use_albumentations false (Isaac-GR00T's torchvision path) is not "
                                                "supported for N1.6; released checkpoints use the albumentations path");
  Gr00tImageGeometry g;
  g.use_albumentations = true;
  g.letter_box = flag("letter_box_transform");
  const auto target = pair("image_target_size");
  const auto crop = pair("image_crop_size");
  // Isaac-GR00T: E = shortest_image_edge or image_target_size[0]; f = crop_fraction or crop / target.
  if (auto it = kwargs.find("shortest_image_edge"); it != kwargs.end() && !it->is_null())
    g.shortest_edge = json_int(*it, "shortest_image_edge", where);
  if (g.shortest_edge && *g.shortest_edge == 0) g.shortest_edge.reset();
  if (!g.shortest_edge) {
    if (!target) throw Error(ErrorCode::format, where + ": neither shortest_image_edge nor image_target_size is set");
    g.shortest_edge = (*target)[0];
  }
  g.target_h = g.target_w = *g.shortest_edge;
  g.crop_size.reset();
  if (auto it = kwargs.find("crop_fraction"); it != kwargs.end() && !it->is_null()) {
    if (!it->is_number()) throw Error(ErrorCode::format, where + ": field 'crop_fraction' is not a number");
    g.crop_fraction = it->get<double>();
  } else if (target && crop) {
    g.crop_fraction = double((*crop)[0]) / double((*target)[0]);
  }
  check_geometry(g);
  g.effective_crop_fraction();
  return g;
}

ResizedSize eagle_smart_resize(int h, int w) {
  constexpr int64_t factor = 28, min_pixels = 4 * 28 * 28, max_pixels = 4096 * 28 * 28, max_side = 500 * 14;
  check_smart_resize_input(h, w);
  int64_t hb = std::min(std::max(factor, py_round(double(h) / double(factor)) * factor), max_side);
  int64_t wb = std::min(std::max(factor, py_round(double(w) / double(factor)) * factor), max_side);
  if (hb * wb > max_pixels) {
    // From the rounded size, floored.
    const double beta = std::sqrt(double(hb * wb) / double(max_pixels));
    hb = int64_t(std::floor(double(hb) / beta / double(factor))) * factor;
    wb = int64_t(std::floor(double(wb) / beta / double(factor))) * factor;
  } else if (hb * wb < min_pixels) {
    // From the original size, rounded up.
    const double beta = std::sqrt(double(min_pixels) / double(int64_t(h) * w));
    hb = int64_t(std::ceil(double(h) * beta / double(factor))) * factor;
    wb = int64_t(std::ceil(double(w) * beta / double(factor))) * factor;
  }
  return {int(hb), int(wb)};
}

EagleFrame eagle_preprocess_frame(const Image& frame, const Gr00tImageGeometry& geometry) {
  return eagle_process_image(gr00t_geometry_albumentations(frame, geometry));
}

EagleFrame eagle_process_image(const Image& shaped) {
  EagleFrame f;
  const ResizedSize s = eagle_smart_resize(shaped.height, shaped.width);
  f.image = resize_bicubic_pil(shaped, s.height, s.width);
  const int64_t H = f.image.height, W = f.image.width, plane = H * W;
  f.pixels.resize(std::size_t(3 * plane));
  // transformers' fused rescale + normalise: mean and std 0.5 * 255 = 127.5, one subtraction and one division.
  for (int64_t i = 0; i < plane; ++i)
    for (int c = 0; c < 3; ++c) f.pixels[std::size_t(c * plane + i)] = (float(f.image.rgb[std::size_t(i * 3 + c)]) - 127.5f) / 127.5f;
  return f;
}

}  // namespace tether::vision
