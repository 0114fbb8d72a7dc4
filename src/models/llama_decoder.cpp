#include "models/llama_decoder.h"

#include "backend/cpu/gemm.h"
#include "backend/cpu/kernels.h"
#include "models/siglip.h"

namespace tether::models {

using namespace tether::cpu;

LlamaConfig LlamaConfig::from_json(const Json& j, const std::string& where) {
  // Defaults are those of transformers' LlamaConfig, which save_pretrained may omit.
  LlamaConfig c;
  c.hidden = json_get_or<int64_t>(j, "hidden_size", 4096, where);
  c.intermediate = json_get_or<int64_t>(j, "intermediate_size", 11008, where);
  c.layers = json_get_or<int64_t>(j, "num_hidden_layers", 32, where);
  c.heads = json_get_or<int64_t>(j, "num_attention_heads", 32, where);
  c.kv_heads = json_get_or<int64_t>(j, "num_key_value_heads", c.heads, where);
  c.head_dim = json_get_or<int64_t>(j, "head_dim", c.hidden / c.heads, where);
  c.vocab = json_get_or<int64_t>(j, "vocab_size", 32000, where);
  c.rms_norm_eps = json_get_or<float>(j, "rms_norm_eps", 1e-6f, where);
  c.attention_bias = json_get_or<bool>(j, "attention_bias", false, where);
  c.mlp_bias = json_get_or<bool>(j, "mlp_bias", false, where);
  const std::string act = json_get_or<std::string>(j, "hidden_act", "silu", where);
  if (act != "silu") throw Error(ErrorCode::unsupported, where + ": text hidden_act '" + act + "' (only silu)");
  if (c.heads % c.kv_heads != 0)
    throw Error(ErrorCode::format, where + ": num_attention_heads is not a multiple of num_key_value_heads");
  return c;
}

void LlamaLayer::load(Weights& w, const std::string& p, const LlamaConfig& cfg, int64_t hidden_size,
                      int64_t intermediate_size, int64_t kv_input, bool cross_attention) {
  hidden = hidden_size;
  intermediate = intermediate_size;
  q_dim = cfg.heads * cfg.head_dim;
  kv_dim = cfg.kv_heads * cfg.head_dim;
  kv_in = kv_input;
  cross = cross_attention;
  input_norm = w.f32(p + "input_layernorm.weight", {hidden});
  post_norm = w.f32(p + "post_attention_layernorm.weight", {hidden});

  const float* q = w.f32(p + "self_attn.q_proj.weight", {q_dim, hidden});
  const float* k = w.f32(p + "self_attn.k_proj.weight", {kv_dim, kv_in});
  const float* v = w.f32(p + "self_attn.v_proj.weight", {kv_dim, kv_in});
  if (cross) {
    qkv_w = stack_rows({{q, q_dim}}, hidden);
    kv_w = stack_rows({{k, kv_dim}, {v, kv_dim}}, kv_in);
  } else {
    qkv_w = stack_rows({{q, q_dim}, {k, kv_dim}, {v, kv_dim}}, hidden);
  }
  if (cfg.attention_bias) {
    const float* qb = w.f32(p + "self_attn.q_proj.bias", {q_dim});
    const float* kb = w.f32(p + "self_attn.k_proj.bias", {kv_dim});
    const float* vb = w.f32(p + "self_attn.v_proj.bias", {kv_dim});
    if (cross) {
      qkv_b.assign(qb, qb + q_dim);
      kv_b = stack_rows({{kb, kv_dim}, {vb, kv_dim}}, 1);
    } else {
      qkv_b = stack_rows({{qb, q_dim}, {kb, kv_dim}, {vb, kv_dim}}, 1);
    }
  }
  o_w = w.f32(p + "self_attn.o_proj.weight", {hidden, q_dim});
  o_b = cfg.attention_bias ? w.f32(p + "self_attn.o_proj.bias", {hidden}) : nullptr;
  gate_up_w = stack_rows({{w.f32(p + "mlp.gate_proj.weight", {intermediate, hidden}), intermediate},
                          {w.f32(p + "mlp.up_proj.weight", {intermediate, hidden}), intermediate}},
                         hidden);
  if (cfg.mlp_bias)
    gate_up_b = stack_rows({{w.f32(p + "mlp.gate_proj.bias", {intermediate}), intermediate},
                            {w.f32(p + "mlp.up_proj.bias", {intermediate}), intermediate}},
                           1);
  down_w = w.f32(p + "mlp.down_proj.weight", {hidden, intermediate});
  down_b = cfg.mlp_bias ? w.f32(p + "mlp.down_proj.bias", {hidden}) : nullptr;
}

void LlamaLayer::finish(const float* attn, int64_t rows, float eps, float* x, std::vector<float>& scratch) const {
  linear(attn, rows, q_dim, o_w, o_b, hidden, x, /*accumulate=*/true);
  const std::size_t need = std::size_t(rows * (hidden + 3 * intermediate));
  if (scratch.size() < need) scratch.resize(need);
  float* normed = scratch.data();
  float* gate_up = normed + rows * hidden;
  float* act = gate_up + rows * 2 * intermediate;
  rms_norm(x, rows, hidden, post_norm, eps, normed);
  linear(normed, rows, hidden, gate_up_w.data(), gate_up_b.empty() ? nullptr : gate_up_b.data(), 2 * intermediate,
         gate_up);
  for (int64_t r = 0; r < rows; ++r)
    silu_mul(gate_up + r * 2 * intermediate, gate_up + r * 2 * intermediate + intermediate, intermediate,
             act + r * intermediate);
  linear(act, rows, intermediate, down_w, down_b, hidden, x, /*accumulate=*/true);
}

}  // namespace tether::models
