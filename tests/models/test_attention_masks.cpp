// Prefix and suffix attention masks against make_att_2d_masks' rule written out by hand for small layouts.
#include <gtest/gtest.h>

#include "models/blocks/attention_masks.h"

using namespace tether::models;

namespace {

// A padded prefix of 4 (item 0: 3 real tokens, item 1: 2) and pi0's suffix: a state token, then 3 action tokens in
// one block ([1, 1, 0, 0]).
TEST(BlockSuffixMasks, StateBlockThenOneActionBlock) {
  const std::vector<uint8_t> pad = {1, 1, 1, 0, 1, 0, 1, 0};
  std::vector<uint8_t> mask;
  std::vector<int64_t> pos;
  block_suffix_masks(pad, 2, 4, {1, 1, 0, 0}, mask, pos);
  ASSERT_EQ(mask.size(), 2u * 4u * 8u);
  EXPECT_EQ(pos, (std::vector<int64_t>{3, 4, 5, 6, 2, 3, 4, 5}));
  const std::vector<uint8_t> item1 = {
      1, 0, 1, 0, 1, 0, 0, 0,  // the state sees the real prefix and itself
      1, 0, 1, 0, 1, 1, 1, 1,  // each action sees the prefix, the state and every action
      1, 0, 1, 0, 1, 1, 1, 1,
      1, 0, 1, 0, 1, 1, 1, 1,
  };
  EXPECT_EQ(std::vector<uint8_t>(mask.begin() + 32, mask.end()), item1);
}

// SmolVLA's causal suffix is the special case of one block per token.
TEST(BlockSuffixMasks, OneBlockPerTokenIsTheCausalSuffix) {
  const std::vector<uint8_t> pad = {1, 1, 0, 1, 0, 1};
  std::vector<uint8_t> mask, joint, cross;
  std::vector<int64_t> pos, joint_pos, cross_pos;
  block_suffix_masks(pad, 2, 3, {1, 1, 1}, mask, pos);
  causal_suffix_masks(pad, 2, 3, 3, joint, cross, joint_pos, cross_pos);
  EXPECT_EQ(mask, joint);
  EXPECT_EQ(pos, joint_pos);
}

// The prefix of pi0 is one bidirectional block over its real tokens; positions skip masked ones.
TEST(PrefixMasks, OneBlockSkipsMaskedTokens) {
  const std::vector<uint8_t> pad = {1, 0, 1, 1};
  const std::vector<int8_t> att = {0, 0, 0, 0};
  std::vector<uint8_t> mask;
  std::vector<int64_t> pos;
  prefix_masks(pad, att, 1, 4, mask, pos);
  EXPECT_EQ(pos, (std::vector<int64_t>{0, 0, 1, 2}));
  EXPECT_EQ(mask, (std::vector<uint8_t>{1, 0, 1, 1, 0, 0, 0, 0, 1, 0, 1, 1, 1, 0, 1, 1}));
}

}  // namespace
