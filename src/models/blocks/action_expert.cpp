// Action experts over a cached prefix (see action_expert.h).
#include "models/blocks/action_expert.h"

#include <cmath>

#include "models/blocks/linear.h"

namespace tether::models {

using backend::Ptr;

void ActionExpert::load(backend::Backend& be, Weights& w, const std::string& prefix, const DecoderConfig& cfg,
                        int64_t hidden, int64_t intermediate, const std::vector<DecoderLayer::Attention>& kinds,
                        int64_t kv_in, cpu::Precision precision) {
  cfg_ = cfg;
  cfg_.hidden = hidden;
  cfg_.intermediate = intermediate;
  layers_.resize(kinds.size());
  for (std::size_t e = 0; e < kinds.size(); ++e) {
    const bool cross = kinds[e] == DecoderLayer::Attention::cross;
    layers_[e].load(be, w, prefix + std::to_string(e) + ".", cfg_, hidden, intermediate, cross ? kv_in : hidden, kinds[e],
                    precision);
  }
  routes_.clear();
  for (std::size_t e = 0; e < kinds.size(); ++e) routes_.push_back({int64_t(e), int64_t(e)});
}

void ActionExpert::set_routes(std::vector<Route> routes) {
  for (const Route& r : routes)
    if (r.expert_layer < 0 || r.expert_layer >= layers())
      throw Error(ErrorCode::internal, "action expert: route to layer " + std::to_string(r.expert_layer) + " of " +
                                           std::to_string(layers()));
  routes_ = std::move(routes);
}

void ActionExpert::prepare(backend::Backend& be, const KvCache& cache, int64_t Lp) {
  const int64_t kv_dim = cfg_.kv_heads * cfg_.head_dim, B = cache.batch;
  cross_k_.resize(routes_.size());
  cross_v_.resize(routes_.size());
  for (std::size_t r = 0; r < routes_.size(); ++r) {
    const DecoderLayer& X = layers_[std::size_t(routes_[r].expert_layer)];
    if (!X.cross()) continue;
    if (cross_k_[r].size() != B * Lp * kv_dim) {
      cross_k_[r] = be.alloc<float>(B * Lp * kv_dim);
      cross_v_[r] = be.alloc<float>(B * Lp * kv_dim);
    }
    // The expert's projections of the (fixed) prefix K/V do not change across denoise steps.
    for (int64_t b = 0; b < B; ++b) {
      be.linear(*X.k_in, cache.k_at(routes_[r].cache_layer, b, 0), Lp, cross_k_[r].at(b * Lp * kv_dim));
      be.linear(*X.v_in, cache.v_at(routes_[r].cache_layer, b, 0), Lp, cross_v_[r].at(b * Lp * kv_dim));
    }
  }
}

void ActionExpert::forward(backend::Backend& be, Ptr<float> x, int64_t B, int64_t len, KvCache& cache, int64_t Lp,
                           Ptr<const int64_t> joint_pos, Ptr<const uint8_t> joint_mask, Ptr<const int64_t> cross_pos,
                           Ptr<const uint8_t> cross_mask, Ptr<const float> modulations) {
  const int64_t E = cfg_.hidden, H = cfg_.heads, KvH = cfg_.kv_heads, hd = cfg_.head_dim;
  const int64_t q_dim = H * hd, kv_dim = KvH * hd, qkv_dim = q_dim + 2 * kv_dim, rows = B * len;
  if (cache.capacity < Lp + len) throw Error(ErrorCode::internal, "action expert: no room after the prefix in the cache");
  scratch_.reserve(be, rows, E, q_dim, kv_dim, cfg_.intermediate);
  const float scale_qk = 1.0f / std::sqrt(float(hd));
  for (std::size_t r = 0; r < routes_.size(); ++r) {
    const DecoderLayer& X = layers_[std::size_t(routes_[r].expert_layer)];
    const int64_t li = routes_[r].cache_layer;
    Conditioning layer_cond;
    if (modulations) {
      const Ptr<const float> m = modulations + routes_[r].expert_layer * 2 * 3 * E;
      layer_cond = {m, m + 3 * E};
    }
    const Conditioning* cond = modulations ? &layer_cond : nullptr;
    norm_input(be, X, cfg_, x, rows, scratch_.normed.at(), cond);
    if (!X.cross()) {
      be.linear(*X.qkv, scratch_.normed.at(), rows, scratch_.qkv.at());
      be.copy_rows(scratch_.qkv.at(), qkv_dim, scratch_.q.at(), q_dim, rows, q_dim);
      for (int64_t b = 0; b < B; ++b) {
        const Ptr<float> kc = cache.k_at(li, b, 0), vc = cache.v_at(li, b, 0);
        be.copy_rows(scratch_.qkv.at(b * len * qkv_dim + q_dim), qkv_dim, kc + Lp * kv_dim, kv_dim, len, kv_dim);
        be.copy_rows(scratch_.qkv.at(b * len * qkv_dim + q_dim + kv_dim), qkv_dim, vc + Lp * kv_dim, kv_dim, len, kv_dim);
        be.rope(scratch_.q.at(b * len * q_dim), 1, len, H, hd, joint_pos + b * len, cfg_.rope_wavelength,
                cfg_.rope_angles);
        be.rope(kc + Lp * kv_dim, 1, len, KvH, hd, joint_pos + b * len, cfg_.rope_wavelength, cfg_.rope_angles);
        be.attention(scratch_.q.at(b * len * q_dim), q_dim, kc, vc, kv_dim, joint_mask + b * len * (Lp + len), 1, len,
                     Lp + len, H, KvH, hd, scale_qk, scratch_.attn.at(b * len * q_dim));
      }
    } else {
      be.linear(*X.qkv, scratch_.normed.at(), rows, scratch_.q.at());
      for (int64_t b = 0; b < B; ++b) {
        be.rope(scratch_.q.at(b * len * q_dim), 1, len, H, hd, cross_pos + b * len, cfg_.rope_wavelength,
                cfg_.rope_angles);
        be.attention(scratch_.q.at(b * len * q_dim), q_dim, cross_k_[r].at(b * Lp * kv_dim), cross_v_[r].at(b * Lp * kv_dim),
                     kv_dim, cross_mask + b * len * Lp, 1, len, Lp, H, KvH, hd, scale_qk,
                     scratch_.attn.at(b * len * q_dim));
      }
    }
    finish_layer(be, X, cfg_, scratch_.attn.at(), rows, x, scratch_, cond);
  }
}

void ActionExpert::adaptive_modulations(backend::Backend& be, Ptr<const float> cond, Ptr<float> out) const {
  const int64_t row = 3 * cfg_.hidden;
  for (std::size_t i = 0; i < layers_.size(); ++i) {
    const DecoderLayer& X = layers_[i];
    if (!X.input_mod) throw Error(ErrorCode::internal, "action expert: modulations asked of a layer without adaptive norms");
    be.linear(*X.input_mod, cond, 1, out + int64_t(2 * i) * row);
    be.linear(*X.post_mod, cond, 1, out + int64_t(2 * i + 1) * row);
  }
}

double ActionExpert::prepare_flops(int64_t batch, int64_t Lp) const {
  double f = 0;
  for (const Route& r : routes_) {
    const DecoderLayer& X = layers_[std::size_t(r.expert_layer)];
    if (X.cross()) f += linear_flops(*X.k_in, batch * Lp) + linear_flops(*X.v_in, batch * Lp);
  }
  return f;
}

double ActionExpert::forward_flops(int64_t batch, int64_t len, int64_t Lp) const {
  double f = 0;
  for (const Route& r : routes_) {
    const DecoderLayer& X = layers_[std::size_t(r.expert_layer)];
    const int64_t keys = X.cross() ? Lp : Lp + len;
    f += linear_flops(*X.qkv, batch * len) + linear_flops(*X.o, batch * len) + linear_flops(*X.gate_up, batch * len) +
         linear_flops(*X.down, batch * len);
    f += 4.0 * double(batch * len) * double(keys) * double(cfg_.heads) * double(cfg_.head_dim);
  }
  return f;
}

}  // namespace tether::models
