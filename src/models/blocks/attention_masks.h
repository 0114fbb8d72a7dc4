// Attention masks and positions of a prefix + action-suffix layout, as lerobot's make_att_2d_masks builds them. They
// are metadata computed on the host and uploaded once per request, as llama.cpp sets its KQ mask.
#pragma once

#include <cstdint>
#include <vector>

namespace tether::models {

// Per item b of a [batch, len] prefix: pad[b, t] = 1 for a real token; att[b, t] = 1 where a new attention block starts
// (earlier tokens cannot see it). Writes mask [batch, len, len] (j visible from i when cumsum(att)[j] <= cumsum(att)[i]
// and both are real) and positions [batch, len] (cumsum(pad) - 1).
void prefix_masks(const std::vector<uint8_t>& pad, const std::vector<int8_t>& att, int64_t batch, int64_t len,
                  std::vector<uint8_t>& mask, std::vector<int64_t>& positions);

// A causal suffix of `len` tokens after a [batch, prefix_len] prefix: each suffix token sees every real prefix token
// and the suffix tokens up to itself. Writes joint_mask [batch, len, prefix_len + len], cross_mask [batch, len,
// prefix_len] (the prefix part alone), joint positions (continuing after the real prefix) and cross positions
// (0..len-1).
void causal_suffix_masks(const std::vector<uint8_t>& prefix_pad, int64_t batch, int64_t prefix_len, int64_t len,
                         std::vector<uint8_t>& joint_mask, std::vector<uint8_t>& cross_mask,
                         std::vector<int64_t>& joint_positions, std::vector<int64_t>& cross_positions);

// A suffix of `block_start.size()` tokens in attention blocks after a [batch, prefix_len] prefix, as make_att_2d_masks
// builds it for pi0's and pi0.5's suffix: block_start[i] = 1 where a new block starts (earlier suffix tokens cannot
// see it). Suffix token i sees every real prefix token and suffix token j when cumsum(block_start)[j] <=
// cumsum(block_start)[i]. Writes mask [batch, len, prefix_len + len] and positions [batch, len] (continuing after the
// real prefix tokens).
void block_suffix_masks(const std::vector<uint8_t>& prefix_pad, int64_t batch, int64_t prefix_len,
                        const std::vector<int8_t>& block_start, std::vector<uint8_t>& mask,
                        std::vector<int64_t>& positions);

}  // namespace tether::models
