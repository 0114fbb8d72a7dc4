#include "models/llama_decoder.h"

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
                      int64_t intermediate_size, int64_t kv_input, bool cross_attention, cpu::Precision precision,
                      bool kv_only) {
  hidden = hidden_size;
  intermediate = intermediate_size;
  q_dim = cfg.heads * cfg.head_dim;
  kv_dim = cfg.kv_heads * cfg.head_dim;
  kv_in = kv_input;
  cross = cross_attention;
  input_norm = w.f32(p + "input_layernorm.weight", {hidden});
  post_norm = w.f32(p + "post_attention_layernorm.weight", {hidden});

  const std::string q = p + "self_attn.q_proj.", k = p + "self_attn.k_proj.", v = p + "self_attn.v_proj.";
  const bool bias = cfg.attention_bias;
  auto biases = [&](std::vector<std::pair<std::string, Shape>> parts) {
    return bias ? w.stacked(parts) : std::vector<float>{};
  };
  if (cross) {
    pack_linear(w, qkv, q.substr(0, q.size() - 1), q_dim, hidden, bias, precision);
    pack_linear(w, k_in, k.substr(0, k.size() - 1), kv_dim, kv_in, bias, precision);
    pack_linear(w, v_in, v.substr(0, v.size() - 1), kv_dim, kv_in, bias, precision);
  } else {
    const auto kv_w = w.stacked({{k + "weight", {kv_dim, kv_in}}, {v + "weight", {kv_dim, kv_in}}});
    const auto kv_b = biases({{k + "bias", {kv_dim}}, {v + "bias", {kv_dim}}});
    if (kv_only) {
      kv.pack(kv_w.data(), 2 * kv_dim, kv_in, bias ? kv_b.data() : nullptr, precision);
    } else {
      std::vector<float> all = w.stacked({{q + "weight", {q_dim, hidden}}});
      all.insert(all.end(), kv_w.begin(), kv_w.end());
      std::vector<float> all_b = biases({{q + "bias", {q_dim}}});
      all_b.insert(all_b.end(), kv_b.begin(), kv_b.end());
      qkv.pack(all.data(), q_dim + 2 * kv_dim, hidden, bias ? all_b.data() : nullptr, precision);
    }
  }
  if (kv_only) return;  // the output of this layer is never read: no o_proj or MLP needed
  pack_linear(w, o, p + "self_attn.o_proj", hidden, q_dim, bias, precision);
  const auto gu_w = w.stacked({{p + "mlp.gate_proj.weight", {intermediate, hidden}},
                               {p + "mlp.up_proj.weight", {intermediate, hidden}}});
  const auto gu_b = cfg.mlp_bias ? w.stacked({{p + "mlp.gate_proj.bias", {intermediate}}, {p + "mlp.up_proj.bias", {intermediate}}})
                                 : std::vector<float>{};
  gate_up.pack(gu_w.data(), 2 * intermediate, hidden, cfg.mlp_bias ? gu_b.data() : nullptr, precision);
  pack_linear(w, down, p + "mlp.down_proj", hidden, intermediate, cfg.mlp_bias, precision);
}

void LlamaLayer::finish(const float* attn, int64_t rows, float eps, float* x, std::vector<float>& scratch) const {
  o.forward(attn, rows, x, /*accumulate=*/true);
  const std::size_t need = std::size_t(rows * (hidden + 3 * intermediate));
  if (scratch.size() < need) scratch.resize(need);
  float* normed = scratch.data();
  float* gu = normed + rows * hidden;  // [gate | up] per row
  float* act = gu + rows * 2 * intermediate;
  rms_norm(x, rows, hidden, post_norm, eps, normed);
  gate_up.forward(normed, rows, gu);
  for (int64_t r = 0; r < rows; ++r)
    silu_mul(gu + r * 2 * intermediate, gu + r * 2 * intermediate + intermediate, intermediate, act + r * intermediate);
  down.forward(act, rows, x, /*accumulate=*/true);
}

}  // namespace tether::models
