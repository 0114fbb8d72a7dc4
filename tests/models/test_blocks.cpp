// The shared decoder and action-expert blocks against a plain double-precision reference, for every norm kind (RMS,
// Gemma's RMS (1 + w), adaptive RMS with scale/shift/gate) and MLP kind (SwiGLU, GeGLU-tanh), with multi-query
// attention over a cached prefix plus the suffix (pi0's joint attention) and over the prefix alone (SmolVLA's
// cross layers). Each block's own flop count is checked against what the backend counted.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "models/blocks/action_expert.h"
#include "models/blocks/attention_masks.h"
#include "models/blocks/decoder.h"
#include "random_checkpoint.h"

using namespace tether;
using namespace tether::models;
using backend::Ptr;

namespace {

constexpr int64_t kHidden = 16, kHeads = 2, kKvHeads = 1, kHeadDim = 8, kInter = 24, kCond = 12;
constexpr int64_t kBatch = 2, kPrefix = 5, kLen = 3;

using test_util::random_vec;
using Checkpoint = test_util::RandomCheckpoint;

// One layer "layers.0." with the projections a joint (self) or cross layer has.
Checkpoint layer_checkpoint(NormKind norm, bool cross) {
  Checkpoint c;
  const std::string p = "layers.0.";
  const int64_t q = kHeads * kHeadDim, kv = kKvHeads * kHeadDim, kv_in = cross ? kv : kHidden;
  uint32_t seed = 1;
  c.add(p + "self_attn.q_proj.weight", {q, kHidden}, seed++);
  c.add(p + "self_attn.k_proj.weight", {kv, kv_in}, seed++);
  c.add(p + "self_attn.v_proj.weight", {kv, kv_in}, seed++);
  c.add(p + "self_attn.o_proj.weight", {kHidden, q}, seed++);
  c.add(p + "mlp.gate_proj.weight", {kInter, kHidden}, seed++);
  c.add(p + "mlp.up_proj.weight", {kInter, kHidden}, seed++);
  c.add(p + "mlp.down_proj.weight", {kHidden, kInter}, seed++);
  for (const char* n : {"input_layernorm", "post_attention_layernorm"}) {
    if (norm == NormKind::adaptive_rms) {
      c.add(p + n + ".dense.weight", {3 * kHidden, kCond}, seed++);
      c.add(p + n + ".dense.bias", {3 * kHidden}, seed++);
    } else {
      c.add(p + n + ".weight", {kHidden}, seed++);
    }
  }
  return c;
}

// y = W x (+ b) for one row.
std::vector<double> matvec(const std::vector<float>& w, const std::vector<double>& x, int64_t n,
                           const std::vector<float>* b = nullptr) {
  const int64_t k = int64_t(x.size());
  std::vector<double> y(static_cast<std::size_t>(n));
  for (int64_t j = 0; j < n; ++j) {
    double acc = b ? (*b)[j] : 0.0;
    for (int64_t i = 0; i < k; ++i) acc += double(w[j * k + i]) * x[i];
    y[j] = acc;
  }
  return y;
}

void rope_ref(std::vector<double>& v, int64_t heads, int64_t pos) {
  const int64_t half = kHeadDim / 2;
  for (int64_t h = 0; h < heads; ++h)
    for (int64_t i = 0; i < half; ++i) {
      const double a = double(pos) / std::pow(10000.0, 2.0 * double(i) / double(kHeadDim));
      const double x1 = v[h * kHeadDim + i], x2 = v[h * kHeadDim + half + i];
      v[h * kHeadDim + i] = x1 * std::cos(a) - x2 * std::sin(a);
      v[h * kHeadDim + half + i] = x2 * std::cos(a) + x1 * std::sin(a);
    }
}

struct Case {
  NormKind norm;
  MlpKind mlp;
  bool cross;
  std::string name() const {
    return std::string(norm == NormKind::rms ? "rms" : norm == NormKind::rms_one_plus ? "rms_one_plus" : "adaptive") +
           (mlp == MlpKind::swiglu ? "_swiglu" : "_geglu") + (cross ? "_cross" : "_joint");
  }
};

class ExpertBlock : public ::testing::TestWithParam<Case> {};

TEST_P(ExpertBlock, MatchesThePlainReference) {
  const Case c = GetParam();
  const Checkpoint ck = layer_checkpoint(c.norm, c.cross);
  Weights w(SafeTensorsFile::open(ck.write("blocks_" + c.name())));
  auto be = backend::make_backend("cpu");

  DecoderConfig cfg;
  cfg.hidden = kHidden;
  cfg.intermediate = kInter;
  cfg.heads = kHeads;
  cfg.kv_heads = kKvHeads;
  cfg.head_dim = kHeadDim;
  cfg.norm = c.norm;
  cfg.mlp = c.mlp;
  cfg.cond_dim = kCond;
  const int64_t kv_dim = kKvHeads * kHeadDim;
  ActionExpert expert;
  expert.load(*be, w, "layers.", cfg, kHidden, kInter,
              {c.cross ? DecoderLayer::Attention::cross : DecoderLayer::Attention::self}, kv_dim, cpu::Precision::fp32);

  // A cached prefix (post-RoPE keys, as the prefix decoder leaves them), the suffix input, masks and positions.
  KvCache cache;
  cache.resize(*be, 1, kBatch, kPrefix + kLen, kv_dim);
  const auto pk = random_vec(kBatch * kPrefix * kv_dim, 100), pv = random_vec(kBatch * kPrefix * kv_dim, 101);
  for (int64_t b = 0; b < kBatch; ++b) {
    be->upload(&pk[b * kPrefix * kv_dim], kPrefix * kv_dim, cache.k_at(0, b, 0));
    be->upload(&pv[b * kPrefix * kv_dim], kPrefix * kv_dim, cache.v_at(0, b, 0));
  }
  const std::vector<uint8_t> prefix_pad = {1, 1, 1, 0, 0, 1, 1, 1, 1, 1};  // item 0 has two padding tokens
  std::vector<uint8_t> joint_mask, cross_mask;
  std::vector<int64_t> joint_pos, cross_pos;
  causal_suffix_masks(prefix_pad, kBatch, kPrefix, kLen, joint_mask, cross_mask, joint_pos, cross_pos);
  auto put = [&](const auto& host) {
    using T = typename std::decay_t<decltype(host)>::value_type;
    auto a = be->alloc<T>(int64_t(host.size()));
    be->upload(host.data(), int64_t(host.size()), a.at());
    return a;
  };
  const auto jm = put(joint_mask), cm = put(cross_mask);
  const auto jp = put(joint_pos), cp = put(cross_pos);
  // One conditioning vector for the whole batch (pi0.5's time: every item is at the same one).
  const auto x0 = random_vec(kBatch * kLen * kHidden, 102, 2.0f), cond = random_vec(kCond, 103);
  const auto xa = put(x0), ca = put(cond);
  backend::Array<float> modulations;
  if (c.norm == NormKind::adaptive_rms) {
    modulations = be->alloc<float>(expert.modulation_size());
    expert.adaptive_modulations(*be, ca.at(), modulations.at());
  }

  expert.prepare(*be, cache, kPrefix);
  const double before = be->flops().total();
  expert.forward(*be, xa.at(), kBatch, kLen, cache, kPrefix, jp.at(), jm.at(), cp.at(), cm.at(), modulations.at());
  EXPECT_DOUBLE_EQ(be->flops().total() - before, expert.forward_flops(kBatch, kLen, kPrefix));
  std::vector<float> got(x0.size());
  be->download(Ptr<const float>(xa.at()), int64_t(got.size()), got.data());

  // The reference, one item at a time.
  const std::string p = "layers.0.";
  auto norm = [&](const std::vector<double>& x, const std::string& which, double* gate_out) {
    double sq = 0;
    for (double v : x) sq += v * v;
    const double inv = 1.0 / std::sqrt(sq / double(kHidden) + double(cfg.rms_norm_eps));
    std::vector<double> y(x.size());
    if (c.norm == NormKind::adaptive_rms) {
      const std::vector<double> cd(cond.begin(), cond.end());
      const auto mod = matvec(ck[p + which + ".dense.weight"], cd, 3 * kHidden, &ck[p + which + ".dense.bias"]);
      for (int64_t i = 0; i < kHidden; ++i) {
        y[i] = x[i] * inv * (1.0 + mod[i]) + mod[kHidden + i];
        gate_out[i] = mod[2 * kHidden + i];
      }
    } else {
      const auto& wt = ck[p + which + ".weight"];
      for (int64_t i = 0; i < kHidden; ++i) {
        y[i] = x[i] * inv * (c.norm == NormKind::rms ? wt[i] : 1.0 + wt[i]);
        gate_out[i] = 1.0;
      }
    }
    return y;
  };
  double worst = 0, scale = 0;
  for (int64_t b = 0; b < kBatch; ++b) {
    std::vector<std::vector<double>> x(kLen), q(kLen), k(kLen), v(kLen);
    std::vector<std::vector<double>> gate1(kLen, std::vector<double>(kHidden)), gate2 = gate1;
    // Keys and values this item's queries attend to: the prefix's (projected again for a cross layer), then the
    // suffix's own for a joint layer.
    std::vector<std::vector<double>> keys, values;
    std::vector<uint8_t> keep;
    for (int64_t t = 0; t < kPrefix; ++t) {
      std::vector<double> kt(pk.begin() + (b * kPrefix + t) * kv_dim, pk.begin() + (b * kPrefix + t + 1) * kv_dim);
      std::vector<double> vt(pv.begin() + (b * kPrefix + t) * kv_dim, pv.begin() + (b * kPrefix + t + 1) * kv_dim);
      if (c.cross) {
        kt = matvec(ck[p + "self_attn.k_proj.weight"], kt, kv_dim);
        vt = matvec(ck[p + "self_attn.v_proj.weight"], vt, kv_dim);
      }
      keys.push_back(kt);
      values.push_back(vt);
      keep.push_back(prefix_pad[b * kPrefix + t]);
    }
    for (int64_t t = 0; t < kLen; ++t) {
      x[t].assign(x0.begin() + (b * kLen + t) * kHidden, x0.begin() + (b * kLen + t + 1) * kHidden);
      const auto n = norm(x[t], "input_layernorm", gate1[t].data());
      q[t] = matvec(ck[p + "self_attn.q_proj.weight"], n, kHeads * kHeadDim);
      rope_ref(q[t], kHeads, c.cross ? cross_pos[b * kLen + t] : joint_pos[b * kLen + t]);
      if (!c.cross) {
        k[t] = matvec(ck[p + "self_attn.k_proj.weight"], n, kv_dim);
        v[t] = matvec(ck[p + "self_attn.v_proj.weight"], n, kv_dim);
        rope_ref(k[t], kKvHeads, joint_pos[b * kLen + t]);
      }
    }
    for (int64_t t = 0; t < kLen; ++t) {
      auto ks = keys, vs = values;
      auto kp = keep;
      if (!c.cross)
        for (int64_t j = 0; j < kLen; ++j) ks.push_back(k[j]), vs.push_back(v[j]), kp.push_back(j <= t);
      std::vector<double> attn(static_cast<std::size_t>(kHeads * kHeadDim), 0.0);
      for (int64_t h = 0; h < kHeads; ++h) {
        std::vector<double> s(ks.size());
        double mx = -1e300, sum = 0;
        for (std::size_t j = 0; j < ks.size(); ++j) {
          double dot = 0;
          for (int64_t d = 0; d < kHeadDim; ++d) dot += q[t][h * kHeadDim + d] * ks[j][d];  // one kv head
          s[j] = dot / std::sqrt(double(kHeadDim));
          if (kp[j]) mx = std::max(mx, s[j]);
        }
        for (std::size_t j = 0; j < ks.size(); ++j) sum += (s[j] = kp[j] ? std::exp(s[j] - mx) : 0.0);
        for (std::size_t j = 0; j < ks.size(); ++j)
          for (int64_t d = 0; d < kHeadDim; ++d) attn[h * kHeadDim + d] += s[j] / sum * vs[j][d];
      }
      const auto o = matvec(ck[p + "self_attn.o_proj.weight"], attn, kHidden);
      std::vector<double> h1(static_cast<std::size_t>(kHidden));
      for (int64_t i = 0; i < kHidden; ++i) h1[i] = x[t][i] + o[i] * gate1[t][i];
      const auto n2 = norm(h1, "post_attention_layernorm", gate2[t].data());
      const auto g = matvec(ck[p + "mlp.gate_proj.weight"], n2, kInter), u = matvec(ck[p + "mlp.up_proj.weight"], n2, kInter);
      std::vector<double> act(static_cast<std::size_t>(kInter));
      for (int64_t i = 0; i < kInter; ++i) {
        const double z = g[i];
        const double a = c.mlp == MlpKind::swiglu ? z / (1 + std::exp(-z))
                                                  : 0.5 * z * (1 + std::tanh(std::sqrt(2 / M_PI) * (z + 0.044715 * z * z * z)));
        act[i] = a * u[i];
      }
      const auto down = matvec(ck[p + "mlp.down_proj.weight"], act, kHidden);
      for (int64_t i = 0; i < kHidden; ++i) {
        const double want = h1[i] + down[i] * gate2[t][i];
        worst = std::max(worst, std::abs(want - double(got[(b * kLen + t) * kHidden + i])));
        scale = std::max(scale, std::abs(want));
      }
    }
  }
  std::printf("[ rel|diff| ] expert layer %-30s %.3e\n", c.name().c_str(), worst / scale);
  EXPECT_LT(worst / scale, 1e-5);
}

INSTANTIATE_TEST_SUITE_P(
    EveryNormAndMlp, ExpertBlock,
    ::testing::Values(Case{NormKind::rms, MlpKind::swiglu, false}, Case{NormKind::rms, MlpKind::swiglu, true},
                      Case{NormKind::rms_one_plus, MlpKind::geglu_tanh, false},
                      Case{NormKind::adaptive_rms, MlpKind::geglu_tanh, false},
                      Case{NormKind::adaptive_rms, MlpKind::swiglu, true}),
    [](const auto& info) { return info.param.name(); });

}  // namespace
