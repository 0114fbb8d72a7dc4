// Prefix and suffix attention masks (see attention_masks.h).
#include "models/blocks/attention_masks.h"

namespace tether::models {

void prefix_masks(const std::vector<uint8_t>& pad, const std::vector<int8_t>& att, int64_t B, int64_t L,
                  std::vector<uint8_t>& mask, std::vector<int64_t>& positions) {
  mask.assign(std::size_t(B * L * L), 0);
  positions.assign(std::size_t(B * L), 0);
  std::vector<int64_t> cum(static_cast<std::size_t>(L));
  for (int64_t b = 0; b < B; ++b) {
    int64_t acc = 0, pos = 0;
    for (int64_t t = 0; t < L; ++t) {
      acc += att[b * L + t];
      cum[t] = acc;
      pos += pad[b * L + t];
      positions[b * L + t] = pos - 1;
    }
    for (int64_t i = 0; i < L; ++i)
      for (int64_t j = 0; j < L; ++j)
        mask[(b * L + i) * L + j] = cum[j] <= cum[i] && pad[b * L + i] && pad[b * L + j];
  }
}

void causal_suffix_masks(const std::vector<uint8_t>& prefix_pad, int64_t B, int64_t Lp, int64_t C,
                         std::vector<uint8_t>& joint_mask, std::vector<uint8_t>& cross_mask,
                         std::vector<int64_t>& joint_positions, std::vector<int64_t>& cross_positions) {
  joint_mask.assign(std::size_t(B * C * (Lp + C)), 0);
  cross_mask.assign(std::size_t(B * C * Lp), 0);
  joint_positions.assign(std::size_t(B * C), 0);
  cross_positions.assign(std::size_t(B * C), 0);
  for (int64_t b = 0; b < B; ++b) {
    int64_t valid = 0;
    for (int64_t t = 0; t < Lp; ++t) valid += prefix_pad[b * Lp + t];
    for (int64_t i = 0; i < C; ++i) {
      joint_positions[b * C + i] = valid + i;
      cross_positions[b * C + i] = i;
      uint8_t* srow = &joint_mask[(b * C + i) * (Lp + C)];
      uint8_t* crow = &cross_mask[(b * C + i) * Lp];
      for (int64_t t = 0; t < Lp; ++t) srow[t] = crow[t] = prefix_pad[b * Lp + t];
      for (int64_t j = 0; j < C; ++j) srow[Lp + j] = j <= i;
    }
  }
}

void block_suffix_masks(const std::vector<uint8_t>& prefix_pad, int64_t B, int64_t Lp,
                        const std::vector<int8_t>& block_start, std::vector<uint8_t>& mask,
                        std::vector<int64_t>& positions) {
  const int64_t C = int64_t(block_start.size());
  mask.assign(std::size_t(B * C * (Lp + C)), 0);
  positions.assign(std::size_t(B * C), 0);
  std::vector<int64_t> cum(static_cast<std::size_t>(C));
  for (int64_t i = 0, acc = 0; i < C; ++i) cum[i] = acc += block_start[i];
  for (int64_t b = 0; b < B; ++b) {
    int64_t valid = 0;
    for (int64_t t = 0; t < Lp; ++t) valid += prefix_pad[b * Lp + t];
    for (int64_t i = 0; i < C; ++i) {
      positions[b * C + i] = valid + i;
      uint8_t* row = &mask[(b * C + i) * (Lp + C)];
      for (int64_t t = 0; t < Lp; ++t) row[t] = prefix_pad[b * Lp + t];
      for (int64_t j = 0; j < C; ++j) row[Lp + j] = cum[j] <= cum[i];
    }
  }
}

}  // namespace tether::models
