// The SigLIP vision-tower block against a plain double-precision reference for both variants it is parameterised
// for: Idefics3/SmolVLM (bucketed position ids, a smaller image reusing the native table, post-norm) and SigLIP as
// PaliGemma uses it (sequential ids on the native grid, here without the post-norm). Its flop count is checked
// against the backend's.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "models/blocks/vision_tower.h"
#include "random_checkpoint.h"

using namespace tether;
using namespace tether::models;
using backend::Ptr;

namespace {

constexpr int64_t kD = 8, kHeads = 2, kF = 12, kPatch = 4, kImage = 12, kSide = kImage / kPatch;

using test_util::random_vec;
using Tower = test_util::RandomCheckpoint;

Tower make_tower() {
  Tower w;
  uint32_t s = 1;
  w.add("embeddings.patch_embedding.weight", {kD, 3, kPatch, kPatch}, s++);
  w.add("embeddings.patch_embedding.bias", {kD}, s++);
  w.add("embeddings.position_embedding.weight", {kSide * kSide, kD}, s++);
  w.add("post_layernorm.weight", {kD}, s++);
  w.add("post_layernorm.bias", {kD}, s++);
  const std::string p = "encoder.layers.0.";
  for (const char* n : {"layer_norm1", "layer_norm2"}) {
    w.add(p + n + ".weight", {kD}, s++);
    w.add(p + n + ".bias", {kD}, s++);
  }
  for (const char* n : {"self_attn.q_proj", "self_attn.k_proj", "self_attn.v_proj", "self_attn.out_proj"}) {
    w.add(p + n + ".weight", {kD, kD}, s++);
    w.add(p + n + ".bias", {kD}, s++);
  }
  w.add(p + "mlp.fc1.weight", {kF, kD}, s++);
  w.add(p + "mlp.fc1.bias", {kF}, s++);
  w.add(p + "mlp.fc2.weight", {kD, kF}, s++);
  w.add(p + "mlp.fc2.bias", {kD}, s++);
  return w;
}

using Rows = std::vector<std::vector<double>>;

Rows linear_ref(const Tower& w, const std::string& name, const Rows& x, int64_t n) {
  const auto& W = w[name + ".weight"];
  const auto& b = w[name + ".bias"];
  Rows y(x.size(), std::vector<double>(static_cast<std::size_t>(n)));
  for (std::size_t r = 0; r < x.size(); ++r)
    for (int64_t j = 0; j < n; ++j) {
      double acc = b[j];
      for (std::size_t i = 0; i < x[r].size(); ++i) acc += W[j * x[r].size() + i] * x[r][i];
      y[r][j] = acc;
    }
  return y;
}

Rows layer_norm_ref(const Tower& w, const std::string& name, const Rows& x) {
  Rows y = x;
  for (auto& row : y) {
    double mean = 0, var = 0;
    for (double v : row) mean += v;
    mean /= double(row.size());
    for (double v : row) var += (v - mean) * (v - mean);
    var /= double(row.size());
    for (std::size_t i = 0; i < row.size(); ++i)
      row[i] = (row[i] - mean) / std::sqrt(var + 1e-6) * w[name + ".weight"][i] + w[name + ".bias"][i];
  }
  return y;
}

// One image [3, h, w] through the tower, given each patch's position id.
Rows tower_ref(const Tower& w, const std::vector<float>& px, int64_t h, int64_t wd, const std::vector<int64_t>& ids,
               bool post_norm) {
  const int64_t ph = h / kPatch, pw = wd / kPatch;
  Rows x(static_cast<std::size_t>(ph * pw), std::vector<double>(kD));
  const auto& pe = w["embeddings.patch_embedding.weight"];
  for (int64_t py = 0; py < ph; ++py)
    for (int64_t pxx = 0; pxx < pw; ++pxx)
      for (int64_t e = 0; e < kD; ++e) {
        double acc = w["embeddings.patch_embedding.bias"][e];
        for (int64_t c = 0; c < 3; ++c)
          for (int64_t i = 0; i < kPatch; ++i)
            for (int64_t j = 0; j < kPatch; ++j)
              acc += double(px[(c * h + py * kPatch + i) * wd + pxx * kPatch + j]) * pe[((e * 3 + c) * kPatch + i) * kPatch + j];
        x[py * pw + pxx][e] = acc + w["embeddings.position_embedding.weight"][ids[py * pw + pxx] * kD + e];
      }
  const std::string p = "encoder.layers.0.";
  const Rows n1 = layer_norm_ref(w, p + "layer_norm1", x);
  const Rows q = linear_ref(w, p + "self_attn.q_proj", n1, kD), k = linear_ref(w, p + "self_attn.k_proj", n1, kD),
             v = linear_ref(w, p + "self_attn.v_proj", n1, kD);
  const int64_t hd = kD / kHeads;
  Rows attn(x.size(), std::vector<double>(kD, 0.0));
  for (std::size_t i = 0; i < x.size(); ++i)
    for (int64_t hh = 0; hh < kHeads; ++hh) {
      std::vector<double> s(x.size());
      double mx = -1e300, sum = 0;
      for (std::size_t j = 0; j < x.size(); ++j) {
        double dot = 0;
        for (int64_t d = 0; d < hd; ++d) dot += q[i][hh * hd + d] * k[j][hh * hd + d];
        mx = std::max(mx, s[j] = dot / std::sqrt(double(hd)));
      }
      for (auto& e : s) sum += (e = std::exp(e - mx));
      for (std::size_t j = 0; j < x.size(); ++j)
        for (int64_t d = 0; d < hd; ++d) attn[i][hh * hd + d] += s[j] / sum * v[j][hh * hd + d];
    }
  const Rows o = linear_ref(w, p + "self_attn.out_proj", attn, kD);
  for (std::size_t i = 0; i < x.size(); ++i)
    for (int64_t e = 0; e < kD; ++e) x[i][e] += o[i][e];
  Rows m = linear_ref(w, p + "mlp.fc1", layer_norm_ref(w, p + "layer_norm2", x), kF);
  for (auto& row : m)
    for (auto& z : row) z = 0.5 * z * (1 + std::tanh(std::sqrt(2 / M_PI) * (z + 0.044715 * z * z * z)));
  const Rows f2 = linear_ref(w, p + "mlp.fc2", m, kD);
  for (std::size_t i = 0; i < x.size(); ++i)
    for (int64_t e = 0; e < kD; ++e) x[i][e] += f2[i][e];
  return post_norm ? layer_norm_ref(w, "post_layernorm", x) : x;
}

// The tower's weights written as a checkpoint and loaded into a block of the given variant.
VisionTower load_tower(backend::Backend& be, const Tower& w, VisionConfig::PositionIds ids_kind, bool post_norm) {
  Weights weights(SafeTensorsFile::open(w.write("vision_tower")));
  VisionConfig cfg;
  cfg.hidden = kD;
  cfg.intermediate = kF;
  cfg.layers = 1;
  cfg.heads = kHeads;
  cfg.patch = kPatch;
  cfg.image_size = kImage;
  cfg.position_ids = ids_kind;
  cfg.post_norm = post_norm;
  VisionTower tower;
  tower.load(be, weights, "", cfg, cpu::Precision::fp32);
  return tower;
}

void check_variant(VisionConfig::PositionIds ids_kind, bool post_norm, int64_t h, int64_t wd,
                   const std::vector<int64_t>& expected_ids) {
  const Tower w = make_tower();
  auto be = backend::make_backend("cpu");
  VisionTower tower = load_tower(*be, w, ids_kind, post_norm);

  const int64_t B = 2, n = tower.num_patches(h, wd);
  const auto px = random_vec(B * 3 * h * wd, 77, 1.0f);
  auto pa = be->alloc<float>(int64_t(px.size()));
  be->upload(px.data(), int64_t(px.size()), pa.at());
  auto ya = be->alloc<float>(B * n * kD);
  const double before = be->flops().total();
  tower.forward(*be, pa.at(), B, h, wd, ya.at());
  EXPECT_DOUBLE_EQ(be->flops().total() - before, tower.flops(B, h, wd));
  std::vector<float> got(static_cast<std::size_t>(B * n * kD));
  be->download(Ptr<const float>(ya.at()), int64_t(got.size()), got.data());
  double worst = 0, scale = 0;
  for (int64_t b = 0; b < B; ++b) {
    const std::vector<float> img(px.begin() + b * 3 * h * wd, px.begin() + (b + 1) * 3 * h * wd);
    const Rows want = tower_ref(w, img, h, wd, expected_ids, post_norm);
    for (int64_t t = 0; t < n; ++t)
      for (int64_t e = 0; e < kD; ++e) {
        worst = std::max(worst, std::abs(want[t][e] - double(got[(b * n + t) * kD + e])));
        scale = std::max(scale, std::abs(want[t][e]));
      }
  }
  std::printf("[ rel|diff| ] vision tower %s%s %lldx%lld: %.3e\n",
              ids_kind == VisionConfig::PositionIds::bucketed ? "bucketed" : "sequential", post_norm ? " +post-norm" : "",
              static_cast<long long>(h), static_cast<long long>(wd), worst / scale);
  EXPECT_LT(worst / scale, 1e-5);
}

}  // namespace

TEST(VisionTowerBlock, SigLipSequentialIdsWithoutPostNorm) {
  std::vector<int64_t> ids(kSide * kSide);
  for (int64_t i = 0; i < kSide * kSide; ++i) ids[i] = i;
  check_variant(VisionConfig::PositionIds::sequential, false, kImage, kImage, ids);
}

TEST(VisionTowerBlock, Idefics3BucketedIdsOnASmallerImage) {
  // An 8x12 image is a 2x3 patch grid; rows bucket to native rows 0 and 1 (fractions 0 and 1/2 against
  // boundaries 1/3, 2/3), columns to 0, 1, 2.
  check_variant(VisionConfig::PositionIds::bucketed, true, 8, 12, {0, 1, 2, 3 * 1 + 0, 3 * 1 + 1, 3 * 1 + 2});
}

TEST(VisionTowerBlock, SequentialIdsNeedTheNativeSize) {
  auto be = backend::make_backend("cpu");
  VisionTower tower = load_tower(*be, make_tower(), VisionConfig::PositionIds::sequential, true);
  auto pa = be->alloc<float>(3 * 8 * 12), ya = be->alloc<float>(6 * kD);
  EXPECT_THROW(tower.forward(*be, pa.at(), 1, 8, 12, ya.at()), Error);
}
