// Llama-style decoder layer weights and the pieces of its forward pass (RMSNorm, projections, SwiGLU MLP).
// Families that interleave two decoders (SmolVLA's VLM + action expert) compose these pieces themselves.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "backend/cpu/packed_linear.h"
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
  cpu::PackedLinear qkv;         // self: [q | k | v] from the layer input; cross: q only
  cpu::PackedLinear k_in, v_in;  // cross only: k and v projections of the other stream's K and V
  cpu::PackedLinear kv;          // self, on request: [k | v] alone, for a last layer whose output is never read
  cpu::PackedLinear o, gate_up, down;  // gate_up: [gate | up]

  void load(Weights& w, const std::string& prefix, const LlamaConfig& cfg, int64_t hidden, int64_t intermediate,
            int64_t kv_in, bool cross, cpu::Precision precision, bool kv_only = false);

  // x += o_proj(attn) ; x += down(silu(gate(n)) * up(n)) with n = post_norm(x). `scratch` grows as needed.
  void finish(const float* attn, int64_t rows, float eps, float* x, std::vector<float>& scratch) const;
};

}  // namespace tether::models
