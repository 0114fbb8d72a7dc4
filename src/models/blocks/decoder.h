// A transformer decoder stack with a cached prefix, parameterised the way the VLA backbones differ: norm kind (RMS,
// Gemma's RMS (1 + w), adaptive RMS with scale/shift/gate), MLP kind (SwiGLU, GeGLU-tanh), grouped or multi-query
// attention, RoPE and the embedding scale.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "core/json_util.h"
#include "models/weights.h"

namespace tether::models {

enum class NormKind { rms, rms_one_plus, adaptive_rms };
enum class MlpKind { swiglu, geglu_tanh };

struct DecoderConfig {
  int64_t hidden = 0, intermediate = 0, heads = 0, kv_heads = 0, head_dim = 0, layers = 0, vocab = 0;
  float rms_norm_eps = 1e-6f;
  bool attention_bias = false, mlp_bias = false;
  NormKind norm = NormKind::rms;
  MlpKind mlp = MlpKind::swiglu;
  float rope_wavelength = 10000.0f;
  backend::RopeAngles rope_angles = backend::RopeAngles::timescale_division;
  float embedding_scale = 1.0f;  // token embeddings are multiplied by this (sqrt(hidden) for Gemma and SmolVLA)
  int64_t cond_dim = 0;          // adaptive norms: width of the conditioning vector (pi0.5's time embedding)
  bool qk_norm = false;          // Qwen3: an RMSNorm over each head of q and k (`q_norm`, `k_norm`) before RoPE
  // Reads a transformers LlamaConfig object; absent fields take the upstream class defaults.
  static DecoderConfig from_llama_json(const Json& j, const std::string& where);
};

// Matrix-product flops (2 per multiply-add) of one layer over `rows` tokens attending to `keys` keys, for benchmarks.
struct LayerFlops {
  double linear = 0, attention = 0;
  double total() const { return linear + attention; }
};

// Per-layer post-RoPE keys and values of a batch: [batch, capacity, kv_dim] each, the prefix first, then room for
// the tokens that attend jointly with it (an action expert's suffix).
struct KvCache {
  int64_t batch = 0, capacity = 0, kv_dim = 0;
  std::vector<backend::Array<float>> k, v;
  void resize(backend::Backend& be, int64_t layers, int64_t batch, int64_t capacity, int64_t kv_dim);
  backend::Ptr<float> k_at(int64_t layer, int64_t item, int64_t token) const {
    return k[std::size_t(layer)].at((item * capacity + token) * kv_dim);
  }
  backend::Ptr<float> v_at(int64_t layer, int64_t item, int64_t token) const {
    return v[std::size_t(layer)].at((item * capacity + token) * kv_dim);
  }
};

// One decoder layer's weights. Self-attention layers project q, k, v from their own input in one GEMM; cross layers
// project only q, and k / v from another stream's keys and values whose width is `kv_in`.
struct DecoderLayer {
  enum class Attention { self, cross };
  int64_t hidden = 0, intermediate = 0, q_dim = 0, kv_dim = 0, kv_in = 0;
  Attention attention = Attention::self;
  NormKind norm = NormKind::rms;
  MlpKind mlp = MlpKind::swiglu;
  backend::Array<float> input_norm, post_norm;  // weights of the two norms (empty for adaptive norms)
  backend::Array<float> q_norm, k_norm;         // per-head norms of q and k [head_dim] (DecoderConfig::qk_norm)
  // Adaptive norms: the conditioning's [scale | shift | gate] for each norm (`<norm>.dense`, cond_dim -> 3 * hidden).
  std::unique_ptr<backend::LinearWeights> input_mod, post_mod;
  std::unique_ptr<backend::LinearWeights> qkv;  // self: [q | k | v]; cross: q only
  std::unique_ptr<backend::LinearWeights> k_in, v_in;  // cross: k and v from the other stream
  std::unique_ptr<backend::LinearWeights> kv;   // self, on request: [k | v] alone, for a last layer never read
  std::unique_ptr<backend::LinearWeights> o, gate_up, down;  // gate_up: [gate | up]

  bool cross() const { return attention == Attention::cross; }
  void load(backend::Backend& be, Weights& w, const std::string& prefix, const DecoderConfig& cfg, int64_t hidden,
            int64_t intermediate, int64_t kv_in, Attention attention, cpu::Precision precision, bool kv_only = false);
  LayerFlops flops(int64_t rows, int64_t keys, int64_t heads, int64_t head_dim) const;
};

// One adaptive layer's modulations, each [scale | shift | gate] (3 * hidden) from linear(conditioning): its input
// norm's and its post-attention norm's. One row serves every row of the pass (pi0.5: every item is at the same time).
struct Conditioning {
  backend::Ptr<const float> input, post;
};

// Scratch activations of a decoder pass, sized once per shape: the steady state allocates nothing.
struct DecoderScratch {
  backend::Array<float> normed, qkv, q, attn, mlp, branch;
  void reserve(backend::Backend& be, int64_t rows, int64_t hidden, int64_t q_dim, int64_t kv_dim, int64_t intermediate);
};

// The two halves of a layer's forward pass, shared by every stack and expert. `cond` is needed by adaptive norms only.
// Input norm: out = norm(x) (the layer's first norm).
void norm_input(backend::Backend& be, const DecoderLayer& L, const DecoderConfig& cfg, backend::Ptr<const float> x,
                int64_t rows, backend::Ptr<float> out, const Conditioning* cond = nullptr);
// After attention: x += o(attn); x += mlp(post_norm(x)); with adaptive norms each branch is scaled by its gate.
void finish_layer(backend::Backend& be, const DecoderLayer& L, const DecoderConfig& cfg, backend::Ptr<const float> attn,
                  int64_t rows, backend::Ptr<float> x, DecoderScratch& s, const Conditioning* cond = nullptr);

// RoPE angles the model computed itself, one row per token of the batch ([batch * len, head_dim / 2] each), for
// position schemes the decoder does not derive from a position (Qwen3-VL's interleaved multimodal RoPE).
struct RotaryTable {
  backend::Ptr<const float> cos, sin;
};

// A decoder over a prefix whose keys and values are kept for later tokens. The last layer may be `kv_only`: when
// nothing reads the stack's output, only that layer's K/V are computed.
class DecoderStack {
 public:
  void load(backend::Backend& be, Weights& w, const std::string& prefix, const DecoderConfig& cfg, int64_t layers,
            cpu::Precision precision, bool last_kv_only);
  const DecoderConfig& config() const { return cfg_; }
  int64_t layers() const { return int64_t(layers_.size()); }
  // x [batch, len, hidden] in place; positions [batch, len]; mask [batch, len, len] (nonzero: may attend). Leaves
  // every layer's post-RoPE K/V in cache rows [0, len).
  void forward(backend::Backend& be, backend::Ptr<float> x, int64_t batch, int64_t len,
               backend::Ptr<const int64_t> positions, backend::Ptr<const uint8_t> mask, KvCache& cache);
  // The same with the angles given, and `after_layer(i)` called after layer i has updated x (where a model adds
  // something between layers: Qwen3-VL's DeepStack features).
  void forward(backend::Backend& be, backend::Ptr<float> x, int64_t batch, int64_t len, const RotaryTable& rotary,
               backend::Ptr<const uint8_t> mask, KvCache& cache, const std::function<void(int64_t layer)>& after_layer);
  LayerFlops flops(int64_t batch, int64_t len) const;

 private:
  void run(backend::Backend& be, backend::Ptr<float> x, int64_t batch, int64_t len,
           backend::Ptr<const int64_t> positions, const RotaryTable* rotary, backend::Ptr<const uint8_t> mask,
           KvCache& cache, const std::function<void(int64_t layer)>* after_layer);

  DecoderConfig cfg_;
  std::vector<DecoderLayer> layers_;
  DecoderScratch scratch_;
};

}  // namespace tether::models
