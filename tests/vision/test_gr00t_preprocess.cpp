// GR00T N1.7 camera-frame preprocessing parity against the upstream code itself (fixtures written by
// tools/oracle/gr00t_vision_fixtures.py): OpenCV INTER_AREA, torchvision's uint8 bicubic antialias resize, Pillow's
// bicubic resize (N1.6),
// lerobot's two eval geometry paths, and transformers' Qwen2VLImageProcessor. uint8 stages must match exactly;
// pixel rows are compared value by value (max |diff| printed, expected 0).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <limits>

#include "core/error.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "vision/area_resize.h"
#include "vision/gr00t_preprocess.h"
#include "vision_test_util.h"

using namespace tether;
using namespace tether::vision;
using namespace tether::vision::test;

namespace {

const SafeTensorsFile& gr00t_fixture(const std::string& name) {
  static std::map<std::string, SafeTensorsFile> files;
  auto it = files.find(name);
  if (it == files.end()) it = files.emplace(name, SafeTensorsFile::open(fixture("gr00t/" + name))).first;
  return it->second;
}

// The generator's `synth` frame, rebuilt here: uint32 arithmetic with wrap-around, so it is bit-identical.
Image synth(int h, int w, uint32_t seed, const std::string& kind = "scene") {
  Image img;
  img.height = h;
  img.width = w;
  img.rgb.resize(size_t(h) * w * 3);
  for (uint32_t y = 0; y < uint32_t(h); ++y)
    for (uint32_t x = 0; x < uint32_t(w); ++x)
      for (uint32_t c = 0; c < 3; ++c) {
        const uint32_t i = (y * uint32_t(w) + x) * 3u + c;
        uint32_t k = i * 2654435761u + seed * 40503u;
        k ^= k >> 15;
        k *= 2246822519u;
        k ^= k >> 13;
        uint32_t v;
        if (kind == "binary") {
          v = (k >> 20) & 1u ? 255u : 0u;
        } else {
          const uint32_t gx = x * 255u / uint32_t(std::max(w - 1, 1));
          const uint32_t gy = y * 255u / uint32_t(std::max(h - 1, 1));
          const uint32_t gxy = (x + y) * 255u / uint32_t(std::max(w + h - 2, 1));
          const uint32_t base = c == 0 ? gx : c == 1 ? gy : gxy;
          v = base * 3u / 4u + ((k >> 24) & 63u);
          if (((x >> 4) + (y >> 4)) & 1u) v = 255u - v;
        }
        img.rgb[i] = uint8_t(v);
      }
  return img;
}

Image synth(const Json& spec) {
  return synth(spec.at("h").get<int>(), spec.at("w").get<int>(), spec.at("seed").get<uint32_t>(),
               spec.value("kind", std::string("scene")));
}

Image image_from_tensor(const Tensor& t) {
  EXPECT_EQ(t.dtype, DType::u8);
  EXPECT_EQ(t.shape.size(), 3u);
  Image img;
  img.height = int(t.dim(0));
  img.width = int(t.dim(1));
  img.rgb.resize(size_t(t.numel()));
  std::memcpy(img.rgb.data(), t.data, img.rgb.size());
  return img;
}

struct ByteDiff {
  int max_abs = 0;
  int64_t mismatched = 0;
};

ByteDiff compare_images(const Image& got, const Image& want) {
  ByteDiff d;
  if (got.height != want.height || got.width != want.width) {
    ADD_FAILURE() << "size " << got.height << "x" << got.width << " vs " << want.height << "x" << want.width;
    d.mismatched = -1;
    return d;
  }
  for (size_t i = 0; i < got.rgb.size(); ++i) {
    const int diff = std::abs(int(got.rgb[i]) - int(want.rgb[i]));
    d.mismatched += diff != 0;
    d.max_abs = std::max(d.max_abs, diff);
  }
  return d;
}

// The lerobot keyword arguments of a geometry case, read through the processor_kwargs parser.
Gr00tImageGeometry geometry_from_case(const Json& c) {
  const Json& kw = c.at("kwargs");
  Json pk = Json::object();
  pk["image_target_size"] = kw.at("image_target_size");
  pk["image_crop_size"] = kw.at("image_crop_size");
  pk["shortest_image_edge"] = kw.at("shortest_image_edge");
  pk["crop_fraction"] = kw.at("crop_fraction");
  pk["letter_box_transform"] = kw.value("letter_box_transform", false);
  pk["use_albumentations"] = c.at("path").get<std::string>() == "albumentations";
  return Gr00tImageGeometry::from_processor_kwargs(pk, "case " + c.at("name").get<std::string>());
}

std::vector<int64_t> i64_values(const Tensor& t) {
  EXPECT_EQ(t.dtype, DType::i64);
  std::vector<int64_t> v(size_t(t.numel()));
  std::memcpy(v.data(), t.data, v.size() * sizeof(int64_t));
  return v;
}

std::vector<double> f64_values(const Tensor& t) {
  EXPECT_EQ(t.dtype, DType::f64);
  std::vector<double> v(size_t(t.numel()));
  std::memcpy(v.data(), t.data, v.size() * sizeof(double));
  return v;
}

// Compares pixel rows against a case's stored full pixel_values, or its sampled rows plus every row's sum.
Diff compare_pixel_rows(const SafeTensorsFile& f, const std::string& name, const PixelPatches& got) {
  const std::string prefix = "qwen/" + name + "/";
  if (f.contains(prefix + "pixel_values")) {
    const Tensor want = f.get(prefix + "pixel_values");
    EXPECT_EQ(want.shape, (Shape{got.grid.patches(), got.row_size})) << name;
    if (int64_t(got.values.size()) != want.numel()) return {1e30, want.numel()};
    return compare(got.values.data(), f32_values(want).data(), want.numel());
  }
  const std::vector<int64_t> rows = i64_values(f.get(prefix + "row_index"));
  const std::vector<float> want = f32_values(f.get(prefix + "rows"));
  Diff d;
  for (size_t k = 0; k < rows.size(); ++k) {
    const Diff r = compare(got.values.data() + rows[k] * got.row_size, want.data() + k * got.row_size, got.row_size);
    d.max_abs = std::max(d.max_abs, r.max_abs);
    d.mismatched += r.mismatched;
  }
  const std::vector<double> sums = f64_values(f.get(prefix + "row_sums"));
  EXPECT_EQ(int64_t(sums.size()), got.grid.patches()) << name;
  for (int64_t r = 0; r < std::min<int64_t>(int64_t(sums.size()), got.grid.patches()); ++r) {
    double s = 0;
    for (int64_t k = 0; k < got.row_size; ++k) s += double(got.values[r * got.row_size + k]);
    // A single pixel one level off moves a row sum by 2 / 127.5; float64 summation noise is ~1e-12.
    EXPECT_NEAR(s, sums[r], 1e-6) << name << " row " << r;
  }
  return d;
}

}  // namespace

TEST(Gr00tVision, SynthFramesMatchTheGenerator) {
  const SafeTensorsFile& f = gr00t_fixture("area.safetensors");
  EXPECT_EQ(compare_images(synth(7, 9, 3), image_from_tensor(f.get("synth/check"))).mismatched, 0);
  EXPECT_EQ(compare_images(synth(5, 6, 4, "binary"), image_from_tensor(f.get("synth/check_binary"))).mismatched, 0);
}

TEST(Gr00tVision, AreaResizeMatchesOpenCv) {
  const SafeTensorsFile& f = gr00t_fixture("area.safetensors");
  const Json cases = metadata_json(f, "cases");
  ASSERT_GE(cases.size(), 20u);
  for (const auto& c : cases) {
    const std::string name = c.at("name");
    const Image want = image_from_tensor(f.get("area/" + name));
    const Image got = resize_area(synth(c.at("frame")), c.at("out")[0].get<int>(), c.at("out")[1].get<int>());
    const ByteDiff d = compare_images(got, want);
    std::printf("  area %-34s max|diff| %d (%lld bytes differ)\n", name.c_str(), d.max_abs, (long long)d.mismatched);
    EXPECT_EQ(d.mismatched, 0) << name;
  }
}

TEST(Gr00tVision, BicubicAntialiasMatchesTorchvision) {
  const SafeTensorsFile& f = gr00t_fixture("bicubic.safetensors");
  const Json cases = metadata_json(f, "cases");
  ASSERT_GE(cases.size(), 10u);
  for (const auto& c : cases) {
    const std::string name = c.at("name");
    const Image want = image_from_tensor(f.get("bicubic/" + name));
    const Image got =
        resize_bicubic_antialias(synth(c.at("frame")), c.at("out")[0].get<int>(), c.at("out")[1].get<int>());
    const ByteDiff d = compare_images(got, want);
    std::printf("  bicubic %-31s max|diff| %d (%lld bytes differ)\n", name.c_str(), d.max_abs,
                (long long)d.mismatched);
    EXPECT_EQ(d.mismatched, 0) << name;
  }
}

TEST(Gr00tVision, PillowBicubicMatchesPillow) {
  const SafeTensorsFile& f = gr00t_fixture("pil_bicubic.safetensors");
  const Json cases = metadata_json(f, "cases");
  ASSERT_GE(cases.size(), 15u);
  for (const auto& c : cases) {
    const std::string name = c.at("name");
    const Image want = image_from_tensor(f.get("pil/" + name));
    const Image got = resize_bicubic_pil(synth(c.at("frame")), c.at("out")[0].get<int>(), c.at("out")[1].get<int>());
    const ByteDiff d = compare_images(got, want);
    std::printf("  pil %-35s max|diff| %d (%lld bytes differ)\n", name.c_str(), d.max_abs, (long long)d.mismatched);
    EXPECT_EQ(d.mismatched, 0) << name;
  }
}

TEST(Gr00tVision, GeometryMatchesLerobotBothPaths) {
  const SafeTensorsFile& f = gr00t_fixture("geometry.safetensors");
  const Json cases = metadata_json(f, "cases");
  int albumentations = 0, torch = 0;
  for (const auto& c : cases) {
    const std::string name = c.at("name"), path = c.at("path");
    const Gr00tImageGeometry g = geometry_from_case(c);
    const Image want = image_from_tensor(f.get(path + "/" + name));
    const Image got = gr00t_geometry(synth(c.at("frame")), g);
    const ByteDiff d = compare_images(got, want);
    std::printf("  %-14s %-36s -> %dx%d max|diff| %d (%lld bytes differ)\n", path.c_str(), name.c_str(), got.height,
                got.width, d.max_abs, (long long)d.mismatched);
    EXPECT_EQ(d.mismatched, 0) << path << " " << name;
    (path == "torch" ? torch : albumentations)++;
  }
  EXPECT_GE(albumentations, 8);
  EXPECT_GE(torch, 3);
}

TEST(Gr00tVision, ReleasedSettingKeepsAspect) {
  // docs/design/gr00t.md: 480x640 with shortest edge 256 and crop fraction 0.95 becomes 256x340.
  Gr00tImageGeometry g;
  g.shortest_edge = 256;
  g.crop_fraction = 0.95;
  g.use_albumentations = true;
  const Image out = gr00t_geometry(synth(480, 640, 1), g);
  EXPECT_EQ(out.height, 256);
  EXPECT_EQ(out.width, 340);
}

TEST(Gr00tVision, QwenImageProcessorMatchesTransformers) {
  const SafeTensorsFile& f = gr00t_fixture("qwen.safetensors");
  const SafeTensorsFile& geo = gr00t_fixture("geometry.safetensors");
  const Json settings = metadata_json(f, "settings");
  const Json cases = metadata_json(f, "cases");
  EXPECT_EQ(Json::parse(f.metadata().at("fixture")).at("processor_class"), "Qwen2VLImageProcessor");
  ASSERT_GE(cases.size(), 8u);
  for (const auto& c : cases) {
    const std::string name = c.at("name"), setting = c.at("setting");
    const QwenImageConfig cfg = QwenImageConfig::from_json(settings.at(setting), "settings " + setting);
    const Json& source = c.at("source");
    const Image frame = source.is_string()
                            ? image_from_tensor(geo.get("albumentations/" + source.get<std::string>().substr(9)))
                            : synth(source);
    const ResizedSize s = qwen_smart_resize(frame.height, frame.width, cfg);
    EXPECT_EQ(s.height, c.at("resized")[0].get<int>()) << name;
    EXPECT_EQ(s.width, c.at("resized")[1].get<int>()) << name;
    if (f.contains("qwen/" + name + "/resized")) {
      const ByteDiff d =
          compare_images(resize_bicubic_antialias(frame, s.height, s.width), image_from_tensor(f.get("qwen/" + name + "/resized")));
      EXPECT_EQ(d.mismatched, 0) << name << " resized image";
    }
    const PixelPatches got = qwen_image_process(frame, cfg);
    EXPECT_EQ(got.grid.t, c.at("grid_thw")[0].get<int64_t>()) << name;
    EXPECT_EQ(got.grid.h, c.at("grid_thw")[1].get<int64_t>()) << name;
    EXPECT_EQ(got.grid.w, c.at("grid_thw")[2].get<int64_t>()) << name;
    EXPECT_EQ(got.grid.patches(), c.at("rows").get<int64_t>()) << name;
    EXPECT_EQ(got.row_size, c.at("row_size").get<int64_t>()) << name;
    const Diff d = compare_pixel_rows(f, name, got);
    std::printf("  qwen %-24s %4dx%-4d -> %4dx%-4d grid %lldx%lld  pixel_values max|diff| %.3g (%lld differ)\n",
                name.c_str(), frame.height, frame.width, s.height, s.width, (long long)got.grid.h,
                (long long)got.grid.w, d.max_abs, (long long)d.mismatched);
    EXPECT_EQ(d.mismatched, 0) << name;
  }
}

TEST(Gr00tVision, FrameToPixelRowsEndToEnd) {
  // The released setting from a raw 480x640 frame to pixel rows, checked against the Qwen case built on
  // lerobot's own geometry output.
  const SafeTensorsFile& geo = gr00t_fixture("geometry.safetensors");
  const SafeTensorsFile& f = gr00t_fixture("qwen.safetensors");
  const Json geo_cases = metadata_json(geo, "cases");
  const Json* e2e = nullptr;
  for (const auto& c : geo_cases)
    if (c.at("name") == "e256_f095_480x640") e2e = &c;
  ASSERT_NE(e2e, nullptr);
  const QwenImageConfig cfg;  // Qwen3-VL defaults = the fixture's "qwen3vl" setting
  const PixelPatches got = gr00t_preprocess_frame(synth(e2e->at("frame")), geometry_from_case(*e2e), cfg);
  EXPECT_EQ(got.grid.t, 1);
  EXPECT_EQ(got.grid.h, 16);
  EXPECT_EQ(got.grid.w, 22);
  EXPECT_EQ(got.row_size, 1536);
  const Diff d = compare_pixel_rows(f, "resize_256x340", got);
  std::printf("  e2e 480x640 -> 256x340 -> 256x352, %lld rows: max|diff| %.3g\n", (long long)got.grid.patches(),
              d.max_abs);
  EXPECT_EQ(d.mismatched, 0);
}

TEST(Gr00tVision, QwenConfigDefaultsAreQwen3Vl) {
  const Json j = Json::parse(R"({
    "size": {"longest_edge": 16777216, "shortest_edge": 65536}, "patch_size": 16, "temporal_patch_size": 2,
    "merge_size": 2, "image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5], "resample": 3,
    "rescale_factor": 0.00392156862745098, "do_rescale": true, "do_normalize": true, "do_resize": true,
    "processor_class": "Qwen3VLProcessor", "image_processor_type": "Qwen2VLImageProcessorFast"})");
  const QwenImageConfig c = QwenImageConfig::from_json(j, "preprocessor_config.json");
  const QwenImageConfig d;
  EXPECT_EQ(c.patch_size, d.patch_size);
  EXPECT_EQ(c.temporal_patch_size, d.temporal_patch_size);
  EXPECT_EQ(c.merge_size, d.merge_size);
  EXPECT_EQ(c.min_pixels, d.min_pixels);
  EXPECT_EQ(c.max_pixels, d.max_pixels);
  EXPECT_EQ(c.image_mean, d.image_mean);
  EXPECT_EQ(c.image_std, d.image_std);
  EXPECT_EQ(c.rescale_factor, d.rescale_factor);
  // Top-level min_pixels / max_pixels override `size`, as the upstream constructor does.
  const QwenImageConfig o = QwenImageConfig::from_json(Json::parse(R"({"min_pixels": 3136, "max_pixels": 12845056})"), "x");
  EXPECT_EQ(o.min_pixels, 3136);
  EXPECT_EQ(o.max_pixels, 12845056);
  // (0.5 * 255) exactly: pixel 0 -> -1, 255 -> 1, 128 -> 0.5 / 127.5.
  Image px;
  px.height = 32;
  px.width = 32;
  px.rgb.assign(32 * 32 * 3, 0);
  px.rgb[0] = 255;
  px.rgb[1] = 128;
  std::vector<float> rows(4 * 1536);
  const PatchGrid grid = qwen_patchify(px, d, rows.data());
  EXPECT_EQ(grid.patches(), 4);
  EXPECT_EQ(rows[0], 1.0f);                                // channel 0, copy 0, (0, 0)
  EXPECT_EQ(rows[256], 1.0f);                              // channel 0, copy 1
  EXPECT_EQ(rows[512], (128.0f - 127.5f) / 127.5f);        // channel 1
  EXPECT_EQ(rows[1], -1.0f);
}

TEST(Gr00tVision, GeometryConfigFollowsLerobot) {
  // No image_target_size: lerobot's N1.7 defaults, and shortest_image_edge / crop_fraction are ignored.
  const Gr00tImageGeometry d = Gr00tImageGeometry::from_processor_kwargs(
      Json::parse(R"({"shortest_image_edge": 300, "crop_fraction": 0.5, "use_albumentations": true})"), "x");
  EXPECT_EQ(d.target_h, 256);
  EXPECT_EQ(d.target_w, 256);
  ASSERT_TRUE(d.crop_size.has_value());
  EXPECT_EQ((*d.crop_size)[0], 230);
  EXPECT_FALSE(d.shortest_edge.has_value());
  EXPECT_FALSE(d.crop_fraction.has_value());
  EXPECT_TRUE(d.use_albumentations);
  EXPECT_EQ(d.effective_crop_fraction().value(), 230.0 / 256.0);
  // The released setting; a non-boolean flag counts as false.
  const Gr00tImageGeometry r = Gr00tImageGeometry::from_processor_kwargs(
      Json::parse(R"({"image_target_size": [256, 256], "image_crop_size": null, "shortest_image_edge": 256,
                      "crop_fraction": 0.95, "use_albumentations": "yes", "letter_box_transform": true})"),
      "x");
  EXPECT_EQ(r.resize_edge(), 256);
  EXPECT_FALSE(r.crop_size.has_value());
  EXPECT_EQ(r.effective_crop_fraction().value(), 0.95);
  EXPECT_FALSE(r.use_albumentations);
  EXPECT_TRUE(r.letter_box);
  // A fraction of exactly 1 crops nothing.
  Gr00tImageGeometry one;
  one.crop_fraction = 1.0;
  EXPECT_FALSE(one.effective_crop_fraction().has_value());
}

TEST(Gr00tVision, GeometryBuildingBlocks) {
  // Python's round, half to even: 5 * 0.5 = 2.5 -> 2, 7 * 0.5 = 3.5 -> 4.
  EXPECT_EQ(shortest_edge_size(4, 5, 2).width, 2);
  EXPECT_EQ(shortest_edge_size(4, 7, 2).width, 4);
  EXPECT_EQ(shortest_edge_size(256, 300, 256).width, 300);  // already there
  EXPECT_EQ(shortest_edge_size(480, 640, 256).width, 341);
  // Letter-box: the top / left get the smaller half of an odd padding.
  Image tall = synth(5, 2, 9);
  const Image sq = letter_box(tall);
  ASSERT_EQ(sq.height, 5);
  ASSERT_EQ(sq.width, 5);
  EXPECT_EQ(sq.rgb[(0 * 5 + 0) * 3], 0);
  EXPECT_EQ(sq.rgb[(0 * 5 + 1) * 3], tall.rgb[0]);  // left pad 1, right pad 2
  EXPECT_EQ(sq.rgb[(0 * 5 + 3) * 3], 0);
  // Centre crop offsets are floored: 5 -> 2 starts at 1.
  const Image crop = center_crop(synth(5, 5, 10), 2, 2);
  EXPECT_EQ(crop.rgb[0], synth(5, 5, 10).rgb[(1 * 5 + 1) * 3]);
}

TEST(Gr00tVision, BadInputIsRefused) {
  const Image empty;
  Gr00tImageGeometry g;
  g.use_albumentations = true;
  const QwenImageConfig q;
  EXPECT_THROW(gr00t_geometry(empty, g), Error);
  EXPECT_THROW(gr00t_geometry_torch(empty, g), Error);
  EXPECT_THROW(qwen_image_process(empty, q), Error);
  EXPECT_THROW(gr00t_preprocess_frame(empty, g, q), Error);
  EXPECT_THROW(resize_bicubic_antialias(empty, 4, 4), Error);
  EXPECT_THROW(resize_area(empty, 4, 4), Error);
  Image bad = synth(4, 4, 1);
  bad.rgb.pop_back();  // buffer and size disagree
  EXPECT_THROW(resize_area(bad, 2, 2), Error);
  EXPECT_THROW(resize_area(synth(4, 4, 1), 0, 2), Error);
  uint8_t px[12] = {};
  EXPECT_THROW(resize_area(px, 2, 2, 5, 1, 1, px), Error);
  EXPECT_THROW(resize_area(nullptr, 2, 2, 3, 1, 1, px), Error);

  // Crop fractions outside (0, 1], given or derived from the crop size.
  const Image frame = synth(48, 64, 2);
  for (double f : {0.0, -0.1, 1.5, std::numeric_limits<double>::quiet_NaN()}) {
    Gr00tImageGeometry b = g;
    b.crop_fraction = f;
    EXPECT_THROW(gr00t_geometry(frame, b), Error) << f;
    b.use_albumentations = false;
    EXPECT_THROW(gr00t_geometry(frame, b), Error) << f;
  }
  EXPECT_THROW(Gr00tImageGeometry::from_processor_kwargs(
                   Json::parse(R"({"image_target_size": [256, 256], "image_crop_size": [300, 300]})"), "x"),
               Error);
  EXPECT_THROW(Gr00tImageGeometry::from_processor_kwargs(
                   Json::parse(R"({"image_target_size": [256, 256], "crop_fraction": 0})"), "x"),
               Error);
  EXPECT_THROW(Gr00tImageGeometry::from_processor_kwargs(
                   Json::parse(R"({"image_target_size": [0, 256]})"), "x"),
               Error);

  // smart_resize refuses aspect ratios above 200, with the sizes upstream refused.
  const SafeTensorsFile& f = gr00t_fixture("qwen.safetensors");
  const Json settings = metadata_json(f, "settings");
  const Json errors = metadata_json(f, "errors");
  ASSERT_GE(errors.size(), 2u);
  for (const auto& e : errors) {
    const QwenImageConfig cfg = QwenImageConfig::from_json(settings.at(e.at("setting").get<std::string>()), "x");
    const Image img = synth(e.at("in")[0].get<int>(), e.at("in")[1].get<int>(), 0);
    EXPECT_THROW(qwen_smart_resize(img.height, img.width, cfg), Error) << e.at("error");
    EXPECT_THROW(qwen_image_process(img, cfg), Error) << e.at("error");
  }
  EXPECT_NO_THROW(qwen_smart_resize(1, 200, q));  // exactly 200 is allowed

  // No frame is too small for the factor upstream (it is scaled up to min_pixels), but patchifying an image
  // that is not a multiple of patch * merge is refused, and so is a processor that skips the resize on one.
  std::vector<float> out(size_t(4) * 1536);
  EXPECT_THROW(qwen_patchify(synth(16, 16, 3), q, out.data()), Error);
  QwenImageConfig no_resize = q;
  no_resize.do_resize = false;
  EXPECT_THROW(qwen_image_process(synth(20, 40, 3), no_resize), Error);
  const PixelPatches tiny = qwen_image_process(synth(3, 5, 4), q);
  EXPECT_GE(tiny.grid.h, 2);
  EXPECT_GE(tiny.grid.w, 2);

  // Config values upstream cannot run.
  EXPECT_THROW(QwenImageConfig::from_json(Json::parse(R"({"resample": 2})"), "x"), Error);
  EXPECT_THROW(QwenImageConfig::from_json(Json::parse(R"({"image_std": [0.5, 0, 0.5]})"), "x"), Error);
  EXPECT_THROW(QwenImageConfig::from_json(Json::parse(R"({"size": {"shortest_edge": 0, "longest_edge": 10}})"), "x"),
               Error);
  EXPECT_THROW(QwenImageConfig::from_json(Json::parse(R"({"patch_size": 0})"), "x"), Error);
}

// GR00T N1.6's Eagle processing per camera (tests/fixtures/gr00t_n16/cases, tools/oracle/gr00t_n16_oracle.py): the
// albumentations geometry, the Eagle smart_resize + Pillow bicubic resize, and the fused normalisation, against the
// oracle's recorded stages. uint8 stages exactly; pixel values to float rounding.
TEST(Gr00tN16Vision, EagleProcessingMatchesTheOracle) {
  namespace fs = std::filesystem;
  const fs::path root = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n16";
  const Json kwargs = read_json_file((root / "checkpoint" / "processor_config.json").string()).at("processor_kwargs");
  const Gr00tImageGeometry g = Gr00tImageGeometry::from_n16_processor_kwargs(kwargs, "processor_config.json");
  int frames = 0;
  for (const auto& entry : fs::directory_iterator(root / "cases")) {
    const SafeTensorsFile oracle = SafeTensorsFile::open((entry.path() / "oracle.safetensors").string());
    const Json files = Json::parse(oracle.metadata().at("input_files"));
    for (auto it = files.begin(); it != files.end(); ++it) {
      const std::string cam = it.key();
      const Image frame = load_image((entry.path() / it->get<std::string>()).string());
      const Image shaped = gr00t_geometry_albumentations(frame, g);
      const Tensor want_shaped = oracle.get("pre.eagle_image." + cam);
      ASSERT_EQ(shaped.height, want_shaped.dim(0)) << cam;
      ASSERT_EQ(shaped.width, want_shaped.dim(1)) << cam;
      EXPECT_EQ(std::memcmp(shaped.rgb.data(), want_shaped.as<uint8_t>(), shaped.rgb.size()), 0) << cam;
      const EagleFrame f = eagle_preprocess_frame(frame, g);
      const Tensor want_fetched = oracle.get("pre.fetched_image." + cam);
      ASSERT_EQ(f.image.height, want_fetched.dim(0)) << cam;
      ASSERT_EQ(f.image.width, want_fetched.dim(1)) << cam;
      EXPECT_EQ(std::memcmp(f.image.rgb.data(), want_fetched.as<uint8_t>(), f.image.rgb.size()), 0) << cam;
      const std::vector<float> want = oracle.get("pre.pixel_values." + cam).to_f32();
      ASSERT_EQ(want.size(), f.pixels.size());
      float diff = 0;
      for (std::size_t i = 0; i < want.size(); ++i) diff = std::max(diff, std::fabs(want[i] - f.pixels[i]));
      std::printf("  [%s/%s] %dx%d -> %dx%d, pixel values max |diff| %.3e\n", entry.path().filename().c_str(),
                  cam.c_str(), frame.height, frame.width, f.image.height, f.image.width, double(diff));
      EXPECT_EQ(diff, 0.0f) << cam;
      ++frames;
    }
  }
  EXPECT_GE(frames, 4);
}

TEST(Gr00tN16Vision, EagleSmartResizeRules) {
  EXPECT_EQ(eagle_smart_resize(56, 75).width, 84);   // round(75 / 28) = 3
  EXPECT_EQ(eagle_smart_resize(56, 187).width, 196); // round(6.68) = 7
  // Too few pixels: scaled up from the original size, rounded up to 28.
  const ResizedSize small = eagle_smart_resize(20, 30);
  EXPECT_EQ(small.height, 56);
  EXPECT_EQ(small.width, 84);
  // Too many: scaled down from the rounded size, floored.
  const ResizedSize big = eagle_smart_resize(4000, 4000);
  EXPECT_LE(int64_t(big.height) * big.width, 4096 * 28 * 28);
  EXPECT_EQ(big.height % 28, 0);
  EXPECT_THROW(eagle_smart_resize(10, 3000), Error);  // aspect ratio past 200
}
