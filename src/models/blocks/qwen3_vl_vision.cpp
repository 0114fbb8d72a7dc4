// Qwen3-VL's vision tower against the backend interface (see qwen3_vl_vision.h).
#include "models/blocks/qwen3_vl_vision.h"

#include <cmath>

#include "core/error.h"
#include "models/blocks/linear.h"

namespace tether::models {

using backend::Activation;
using backend::Ptr;

int64_t Qwen3VisionConfig::grid_side() const { return int64_t(std::llround(std::sqrt(double(num_position_embeddings)))); }

Qwen3VisionConfig Qwen3VisionConfig::from_json(const Json& j, const std::string& where) {
  Qwen3VisionConfig c;
  c.depth = json_get_or<int64_t>(j, "depth", c.depth, where);
  c.hidden = json_get_or<int64_t>(j, "hidden_size", c.hidden, where);
  c.intermediate = json_get_or<int64_t>(j, "intermediate_size", c.intermediate, where);
  c.heads = json_get_or<int64_t>(j, "num_heads", c.heads, where);
  c.channels = json_get_or<int64_t>(j, "in_channels", c.channels, where);
  c.patch = json_get_or<int64_t>(j, "patch_size", c.patch, where);
  c.temporal_patch = json_get_or<int64_t>(j, "temporal_patch_size", c.temporal_patch, where);
  c.merge = json_get_or<int64_t>(j, "spatial_merge_size", c.merge, where);
  c.out_hidden = json_get_or<int64_t>(j, "out_hidden_size", c.out_hidden, where);
  c.num_position_embeddings = json_get_or<int64_t>(j, "num_position_embeddings", c.num_position_embeddings, where);
  if (j.contains("deepstack_visual_indexes")) c.deepstack_indexes = j.at("deepstack_visual_indexes").get<std::vector<int64_t>>();
  const std::string act = json_get_or<std::string>(j, "hidden_act", "gelu_pytorch_tanh", where);
  if (act != "gelu_pytorch_tanh")
    throw Error(ErrorCode::unsupported, where + ": vision hidden_act '" + act + "' (only gelu_pytorch_tanh)");
  if (c.heads <= 0 || c.hidden % c.heads != 0 || c.head_dim() % 4 != 0)
    throw Error(ErrorCode::format, where + ": vision hidden_size / num_heads must be a multiple of 4 (2-D rotary)");
  const int64_t side = c.grid_side();
  if (side * side != c.num_position_embeddings)
    throw Error(ErrorCode::format, where + ": num_position_embeddings " + std::to_string(c.num_position_embeddings) +
                                       " is not a square");
  for (int64_t i : c.deepstack_indexes)
    if (i < 0 || i >= c.depth)
      throw Error(ErrorCode::format, where + ": deepstack_visual_indexes entry " + std::to_string(i) +
                                         " is outside the " + std::to_string(c.depth) + " blocks");
  return c;
}

void Qwen3VisionTower::load_merger(backend::Backend& be, Weights& w, const std::string& p, bool norm_after_merge,
                                   cpu::Precision precision, Merger& m) {
  const int64_t merged = cfg_.hidden * cfg_.merge * cfg_.merge, norm_width = norm_after_merge ? merged : cfg_.hidden;
  m.norm_after_merge = norm_after_merge;
  m.ln_w = be.constant(w.f32(p + "norm.weight", {norm_width}), norm_width);
  m.ln_b = be.constant(w.f32(p + "norm.bias", {norm_width}), norm_width);
  m.fc1 = load_linear(be, w, p + "linear_fc1", merged, merged, true, precision);
  m.fc2 = load_linear(be, w, p + "linear_fc2", cfg_.out_hidden, merged, true, precision);
}

void Qwen3VisionTower::load(backend::Backend& be, Weights& w, const std::string& p, const Qwen3VisionConfig& config,
                            cpu::Precision precision) {
  cfg_ = config;
  const int64_t D = cfg_.hidden, side = cfg_.grid_side();
  // The Conv3d with kernel = stride = (temporal, patch, patch) is one matrix over a pixel row, whose values are in the
  // weight's own (channel, time, y, x) order.
  const std::string pe = p + "patch_embed.proj.";
  const float* pw = w.f32(pe + "weight", {D, cfg_.channels, cfg_.temporal_patch, cfg_.patch, cfg_.patch});
  patch_embed_ = be.pack_linear(pw, D, cfg_.patch_values(), w.f32(pe + "bias", {D}), precision);
  const float* table = w.f32(p + "pos_embed.weight", {side * side, D});
  pos_table_.assign(table, table + side * side * D);

  blocks_.resize(std::size_t(cfg_.depth));
  for (int64_t i = 0; i < cfg_.depth; ++i) {
    const std::string b = p + "blocks." + std::to_string(i) + ".";
    Block& B = blocks_[std::size_t(i)];
    B.ln1_w = be.constant(w.f32(b + "norm1.weight", {D}), D);
    B.ln1_b = be.constant(w.f32(b + "norm1.bias", {D}), D);
    B.ln2_w = be.constant(w.f32(b + "norm2.weight", {D}), D);
    B.ln2_b = be.constant(w.f32(b + "norm2.bias", {D}), D);
    B.qkv = load_linear(be, w, b + "attn.qkv", 3 * D, D, true, precision);
    B.proj = load_linear(be, w, b + "attn.proj", D, D, true, precision);
    B.fc1 = load_linear(be, w, b + "mlp.linear_fc1", cfg_.intermediate, D, true, precision);
    B.fc2 = load_linear(be, w, b + "mlp.linear_fc2", D, cfg_.intermediate, true, precision);
  }
  deepstack_.resize(cfg_.deepstack_indexes.size());
  for (std::size_t k = 0; k < deepstack_.size(); ++k)
    load_merger(be, w, p + "deepstack_merger_list." + std::to_string(k) + ".", true, precision, deepstack_[k]);
  load_merger(be, w, p + "merger.", false, precision, merger_);
  prepared_for_.clear();
}

namespace {

// torch.linspace(0, end, n) in float32, by its scalar rule: a float32 step, the lower half counted up from 0 and the
// upper half back from `end`. (Its vector path rounds some values differently by an ulp; the bilinear weights then
// differ by an ulp, far below the tower's parity tolerance.)
std::vector<float> linspace_f32(float end, int64_t n) {
  std::vector<float> v(std::size_t(std::max<int64_t>(n, 0)));
  if (n == 1) v[0] = 0.0f;
  if (n <= 1) return v;
  const float step = end / float(n - 1);
  for (int64_t i = 0; i < n; ++i) v[std::size_t(i)] = i < n / 2 ? step * float(i) : end - step * float(n - 1 - i);
  return v;
}

}  // namespace

void Qwen3VisionTower::prepare_positions(backend::Backend& be, const std::vector<VisionGrid>& grids) {
  if (!prepared_for_.empty() && prepared_for_.size() == grids.size()) {
    bool same = true;
    for (std::size_t i = 0; i < grids.size(); ++i)
      same = same && grids[i].t == prepared_for_[i].t && grids[i].h == prepared_for_[i].h && grids[i].w == prepared_for_[i].w;
    if (same) return;
  }
  const int64_t D = cfg_.hidden, side = cfg_.grid_side(), m = cfg_.merge, hd = cfg_.head_dim();
  const int64_t quarter = hd / 4;  // rotary frequencies per axis: the head's half is split between rows and columns
  int64_t total = 0;
  for (const VisionGrid& g : grids) total += g.patches();
  std::vector<float> pos(std::size_t(total * D)), cs(std::size_t(total * hd / 2)), sn(cs.size());
  // inv_freq = 1 / 10000^(arange(0, hd/2, 2) / (hd/2)) in float32, as the tower's rotary embedding builds it.
  std::vector<float> inv_freq(static_cast<std::size_t>(quarter));
  for (int64_t i = 0; i < quarter; ++i)
    inv_freq[std::size_t(i)] = 1.0f / float(std::pow(10000.0, double(float(2 * i) / float(hd / 2))));

  int64_t row = 0;
  for (const VisionGrid& g : grids) {
    if (g.h % m != 0 || g.w % m != 0 || g.t < 1)
      throw Error(ErrorCode::invalid_argument, "vision grid " + std::to_string(g.h) + "x" + std::to_string(g.w) +
                                                   " is not a multiple of the merge size " + std::to_string(m));
    // Bilinear weights of the table at linspace(0, side - 1, h) x linspace(0, side - 1, w): each corner's weight is
    // a float32 product, each corner's row scaled by it, and the four summed in order.
    const std::vector<float> hi = linspace_f32(float(side - 1), g.h), wi = linspace_f32(float(side - 1), g.w);
    for (int64_t t = 0; t < g.t; ++t)
      for (int64_t br = 0; br < g.h / m; ++br)
        for (int64_t bc = 0; bc < g.w / m; ++bc)
          for (int64_t ir = 0; ir < m; ++ir)
            for (int64_t ic = 0; ic < m; ++ic, ++row) {
              const int64_t r = br * m + ir, c = bc * m + ic;  // the patch's place in the grid (merge-block order)
              const int64_t r0 = int64_t(hi[std::size_t(r)]), c0 = int64_t(wi[std::size_t(c)]);
              const int64_t r1 = std::min(r0 + 1, side - 1), c1 = std::min(c0 + 1, side - 1);
              const float dh = hi[std::size_t(r)] - float(r0), dw = wi[std::size_t(c)] - float(c0);
              const float w00 = (1.0f - dh) * (1.0f - dw), w01 = (1.0f - dh) * dw, w10 = dh * (1.0f - dw), w11 = dh * dw;
              const float* t00 = &pos_table_[std::size_t((r0 * side + c0) * D)];
              const float* t01 = &pos_table_[std::size_t((r0 * side + c1) * D)];
              const float* t10 = &pos_table_[std::size_t((r1 * side + c0) * D)];
              const float* t11 = &pos_table_[std::size_t((r1 * side + c1) * D)];
              float* out = &pos[std::size_t(row * D)];
              for (int64_t d = 0; d < D; ++d) out[d] = t00[d] * w00 + t01[d] * w01 + t10[d] * w10 + t11[d] * w11;
              // 2-D rotary: the first quarter of frequencies turn with the row, the second with the column.
              float* crow = &cs[std::size_t(row * hd / 2)];
              float* srow = &sn[std::size_t(row * hd / 2)];
              for (int64_t i = 0; i < quarter; ++i) {
                const float ar = float(r) * inv_freq[std::size_t(i)], ac = float(c) * inv_freq[std::size_t(i)];
                crow[i] = std::cos(ar), srow[i] = std::sin(ar);
                crow[quarter + i] = std::cos(ac), srow[quarter + i] = std::sin(ac);
              }
            }
  }
  pos_rows_ = be.alloc<float>(total * D);
  rot_cos_ = be.alloc<float>(total * hd / 2);
  rot_sin_ = be.alloc<float>(total * hd / 2);
  be.upload(pos.data(), total * D, pos_rows_.at());
  be.upload(cs.data(), int64_t(cs.size()), rot_cos_.at());
  be.upload(sn.data(), int64_t(sn.size()), rot_sin_.at());
  prepared_for_ = grids;
}

void Qwen3VisionTower::run_merger(backend::Backend& be, const Merger& mg, Ptr<const float> x, int64_t patches,
                                  Ptr<float> out) {
  const int64_t D = cfg_.hidden, merged = D * cfg_.merge * cfg_.merge, tokens = patches / (cfg_.merge * cfg_.merge);
  // Consecutive rows of one merge block are one row of `merged` values; the norm runs before or after that regrouping.
  if (mg.norm_after_merge) be.layer_norm(x, tokens, merged, mg.ln_w.at(), mg.ln_b.at(), cfg_.layer_norm_eps, merge_tmp_.at());
  else be.layer_norm(x, patches, D, mg.ln_w.at(), mg.ln_b.at(), cfg_.layer_norm_eps, merge_tmp_.at());
  be.linear(*mg.fc1, merge_tmp_.at(), tokens, mlp_.at());
  be.activate(mlp_.at(), tokens * merged, Activation::gelu_erf);
  be.linear(*mg.fc2, mlp_.at(), tokens, out);
}

void Qwen3VisionTower::forward(backend::Backend& be, Ptr<const float> pixels, const std::vector<VisionGrid>& grids,
                               Ptr<float> merged, const std::vector<Ptr<float>>& deepstack, Ptr<float> patch_embeds) {
  if (deepstack.size() != deepstack_.size())
    throw Error(ErrorCode::internal, "vision tower: expected " + std::to_string(deepstack_.size()) + " DeepStack outputs");
  prepare_positions(be, grids);
  const int64_t D = cfg_.hidden, H = cfg_.heads, hd = cfg_.head_dim();
  int64_t N = 0;
  for (const VisionGrid& g : grids) N += g.patches();
  auto grow = [&](backend::Array<float>& a, int64_t n) {
    if (a.size() < n) a = be.alloc<float>(n);
  };
  grow(x_, N * D);
  grow(normed_, N * D);
  grow(qkv_, N * 3 * D);
  grow(q_, N * D);
  grow(k_, N * D);
  grow(v_, N * D);
  grow(attn_, N * D);
  grow(mlp_, N * std::max(cfg_.intermediate, D));  // a block's MLP, or a merger's [tokens, D * merge^2] rows
  grow(merge_tmp_, N * D);

  be.linear(*patch_embed_, pixels, N, x_.at());
  be.add(x_.at(), pos_rows_.at(), N * D, x_.at());
  if (patch_embeds) be.copy_rows(x_.at(), D, patch_embeds, D, N, D);

  const float scale = 1.0f / std::sqrt(float(hd));
  for (int64_t bi = 0; bi < cfg_.depth; ++bi) {
    const Block& B = blocks_[std::size_t(bi)];
    be.layer_norm(x_.at(), N, D, B.ln1_w.at(), B.ln1_b.at(), cfg_.layer_norm_eps, normed_.at());
    be.linear(*B.qkv, normed_.at(), N, qkv_.at());
    be.copy_rows(qkv_.at(), 3 * D, q_.at(), D, N, D);
    be.copy_rows(qkv_.at(D), 3 * D, k_.at(), D, N, D);
    be.copy_rows(qkv_.at(2 * D), 3 * D, v_.at(), D, N, D);
    be.rope_rotate(q_.at(), N, H, hd, rot_cos_.at(), rot_sin_.at());
    be.rope_rotate(k_.at(), N, H, hd, rot_cos_.at(), rot_sin_.at());
    // Each image attends only to itself.
    int64_t off = 0;
    for (const VisionGrid& g : grids) {
      const int64_t n = g.patches();
      be.attention(q_.at(off * D), D, k_.at(off * D), v_.at(off * D), D, Ptr<const uint8_t>(), 1, n, n, H, H, hd, scale,
                   attn_.at(off * D));
      off += n;
    }
    be.linear(*B.proj, attn_.at(), N, x_.at(), /*accumulate=*/true);
    be.layer_norm(x_.at(), N, D, B.ln2_w.at(), B.ln2_b.at(), cfg_.layer_norm_eps, normed_.at());
    be.linear(*B.fc1, normed_.at(), N, mlp_.at());
    be.activate(mlp_.at(), N * cfg_.intermediate, Activation::gelu_tanh);
    be.linear(*B.fc2, mlp_.at(), N, x_.at(), /*accumulate=*/true);
    for (std::size_t k = 0; k < cfg_.deepstack_indexes.size(); ++k)
      if (cfg_.deepstack_indexes[k] == bi) run_merger(be, deepstack_[k], x_.at(), N, deepstack[k]);
  }
  run_merger(be, merger_, x_.at(), N, merged);
}

double Qwen3VisionTower::flops(const std::vector<VisionGrid>& grids) const {
  int64_t N = 0;
  for (const VisionGrid& g : grids) N += g.patches();
  const int64_t tokens = N / (cfg_.merge * cfg_.merge);
  double f = linear_flops(*patch_embed_, N);
  for (const Block& B : blocks_) f += linear_flops(*B.qkv, N) + linear_flops(*B.proj, N) + linear_flops(*B.fc1, N) +
                                      linear_flops(*B.fc2, N);
  for (const VisionGrid& g : grids) f += 4.0 * double(g.patches()) * double(g.patches()) * double(cfg_.hidden);
  for (const Merger* m : {&merger_}) f += linear_flops(*m->fc1, tokens) + linear_flops(*m->fc2, tokens);
  for (const Merger& m : deepstack_) f += linear_flops(*m.fc1, tokens) + linear_flops(*m.fc2, tokens);
  return f;
}

}  // namespace tether::models
