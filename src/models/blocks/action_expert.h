// Action experts: decoders over a suffix of action tokens that read a cached prefix. A joint layer (SmolVLA's
// self-attention layers; every layer of pi0's Gemma expert) writes its own keys and values after the prefix's in the
// same cache layer and attends over both; a cross layer (SmolVLA's interleave) attends to the prefix alone through its
// own projections of the prefix keys and values, computed once per request.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "models/blocks/decoder.h"

namespace tether::models {

class ActionExpert {
 public:
  // One expert layer and the prefix (cache) layer it reads.
  struct Route {
    int64_t expert_layer = 0, cache_layer = 0;
  };
  // layers `prefix + i + "."` for i < kinds.size(), of width `hidden`; `cfg` gives heads, head_dim, norms, MLP and
  // RoPE; cross layers project keys/values of width `kv_in` (the prefix decoder's kv_dim).
  void load(backend::Backend& be, Weights& w, const std::string& prefix, const DecoderConfig& cfg, int64_t hidden,
            int64_t intermediate, const std::vector<DecoderLayer::Attention>& kinds, int64_t kv_in,
            cpu::Precision precision);
  // The order the layers run in and which cache layer each reads.
  void set_routes(std::vector<Route> routes);
  const std::vector<Route>& routes() const { return routes_; }
  const DecoderLayer& layer(int64_t i) const { return layers_[std::size_t(i)]; }
  int64_t layers() const { return int64_t(layers_.size()); }

  // Once per request, after the prefix filled `cache` rows [0, prefix_len): the cross layers' K/V of the prefix.
  void prepare(backend::Backend& be, const KvCache& cache, int64_t prefix_len);
  // x [batch, len, hidden] in place through every routed layer. Joint layers write their K/V to cache rows
  // [prefix_len, prefix_len + len) and attend with joint_mask [batch, len, prefix_len + len]; cross layers attend with
  // cross_mask [batch, len, prefix_len]. Positions [batch, len] each. `modulations`: for adaptive norms (pi0.5's
  // time), as adaptive_modulations() writes them.
  void forward(backend::Backend& be, backend::Ptr<float> x, int64_t batch, int64_t len, KvCache& cache,
               int64_t prefix_len, backend::Ptr<const int64_t> joint_positions, backend::Ptr<const uint8_t> joint_mask,
               backend::Ptr<const int64_t> cross_positions, backend::Ptr<const uint8_t> cross_mask,
               backend::Ptr<const float> modulations = {});
  // Adaptive norms: every layer's input and post-attention modulation from one conditioning vector `cond`
  // [cond_dim], into `out` [modulation_size()]: layer i's input norm at 2 i * 3 hidden, its post norm after it.
  void adaptive_modulations(backend::Backend& be, backend::Ptr<const float> cond, backend::Ptr<float> out) const;
  int64_t modulation_size() const { return 2 * int64_t(layers_.size()) * 3 * cfg_.hidden; }
  // Matrix-product flops of prepare() and of one forward().
  double prepare_flops(int64_t batch, int64_t prefix_len) const;
  double forward_flops(int64_t batch, int64_t len, int64_t prefix_len) const;

 private:
  DecoderConfig cfg_;
  std::vector<DecoderLayer> layers_;
  std::vector<Route> routes_;
  std::vector<backend::Array<float>> cross_k_, cross_v_;  // per route: [batch, prefix_len, kv_dim] (cross layers)
  DecoderScratch scratch_;
};

}  // namespace tether::models
