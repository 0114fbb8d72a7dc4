#include "models/llama_decoder.h"

#include "backend/cpu/gemm.h"
#include "backend/cpu/kernels.h"

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

  const std::string q = p + "self_attn.q_proj.", k = p + "self_attn.k_proj.", v = p + "self_attn.v_proj.";
  if (cross) {
    qkv_w = w.stacked({{q + "weight", {q_dim, hidden}}});
    kv_w = w.stacked({{k + "weight", {kv_dim, kv_in}}, {v + "weight", {kv_dim, kv_in}}});
  } else {
    qkv_w = w.stacked({{q + "weight", {q_dim, hidden}}, {k + "weight", {kv_dim, kv_in}}, {v + "weight", {kv_dim, kv_in}}});
  }
  if (cfg.attention_bias) {
    if (cross) {
      qkv_b = w.stacked({{q + "bias", {q_dim}}});
      kv_b = w.stacked({{k + "bias", {kv_dim}}, {v + "bias", {kv_dim}}});
    } else {
      qkv_b = w.stacked({{q + "bias", {q_dim}}, {k + "bias", {kv_dim}}, {v + "bias", {kv_dim}}});
    }
  }
  o_w = w.f32(p + "self_attn.o_proj.weight", {hidden, q_dim});
  o_b = cfg.attention_bias ? w.f32(p + "self_attn.o_proj.bias", {hidden}) : nullptr;
  gate_up_w = w.stacked({{p + "mlp.gate_proj.weight", {intermediate, hidden}},
                         {p + "mlp.up_proj.weight", {intermediate, hidden}}});
  if (cfg.mlp_bias)
    gate_up_b = w.stacked({{p + "mlp.gate_proj.bias", {intermediate}}, {p + "mlp.up_proj.bias", {intermediate}}});
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
