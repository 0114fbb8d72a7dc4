// Llama-style decoder layer weights and the pieces of its forward pass (RMSNorm, projections, SwiGLU MLP).
// Families that interleave two decoders (SmolVLA's VLM + action expert) compose these pieces themselves.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "core/json_util.h"
#include "models/weights.h"

namespace tether::models {

struct LlamaConfig {
  int64_t hidden = 0, intermediate = 0, heads = 0, kv_heads = 0, head_dim = 0, layers = 0, vocab = 0;
  float rms_norm_eps = 1e-6f;
  bool attention_bias = false, mlp_bias = false;
  // Reads a transformers LlamaConfig object; absent fields take the upstream class defaults.
  static LlamaConfig from_json(const Json& j, const std::string& where);
};

// One decoder layer. Self-attention layers read K/V from their own input (q, k, v fused in one GEMM);
// cross-attention layers project K/V from another stream whose width is `kv_in`.
struct LlamaLayer {
  int64_t hidden = 0, intermediate = 0, q_dim = 0, kv_dim = 0, kv_in = 0;
  bool cross = false;
  const float *input_norm = nullptr, *post_norm = nullptr;
  std::vector<float> qkv_w, qkv_b;     // self: [q_dim + 2 kv_dim, hidden]; cross: q only [q_dim, hidden]
  std::vector<float> kv_w, kv_b;       // cross only: [2 kv_dim, kv_in]
  const float *o_w = nullptr, *o_b = nullptr;
  std::vector<float> gate_up_w, gate_up_b;  // [2 intermediate, hidden]
  const float *down_w = nullptr, *down_b = nullptr;

  void load(Weights& w, const std::string& prefix, const LlamaConfig& cfg, int64_t hidden, int64_t intermediate,
            int64_t kv_in, bool cross);

  const float* qkv_bias() const { return qkv_b.empty() ? nullptr : qkv_b.data(); }
  const float* kv_bias() const { return kv_b.empty() ? nullptr : kv_b.data(); }

  // x += o_proj(attn) ; x += down(silu(gate(n)) * up(n)) with n = post_norm(x). `scratch` grows as needed.
  void finish(const float* attn, int64_t rows, float eps, float* x, std::vector<float>& scratch) const;
};

}  // namespace tether::models
