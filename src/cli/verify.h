// Measuring how far one policy's action chunks are from another's (an export against its source) or from the
// upstream oracle's fixture outputs: shared by `tether export` (the receipt) and `tether validate`.
#pragma once

#include <string>
#include <vector>

#include "policy/policy.h"

namespace tether::cli {

struct CaseDiff {
  std::string name;
  double max_abs = 0, mean_abs = 0;
  int64_t values = 0;
};

// `cases` seeded observations (pseudo-random frames per camera, states, instructions, noise seeds) through both.
std::vector<CaseDiff> compare_seeded(policy::Policy& reference, policy::Policy& candidate, int cases);

// When `reference_dir` is an oracle fixture checkpoint (its parent holds oracle.safetensors and inputs/), the
// fixture's inputs and noise through `candidate`, compared with upstream's robot-unit actions. Empty otherwise.
std::vector<CaseDiff> compare_with_oracle(const std::string& reference_dir, policy::Policy& candidate);

}  // namespace tether::cli
