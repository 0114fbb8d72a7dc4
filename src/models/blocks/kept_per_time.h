// Arrays that a sampler's time alone decides (the adaptive norms' modulations of GR00T's DiT and pi0.5's expert),
// computed the first time a time is seen and kept: every request visits the same few times, so the weight-streaming
// matrix-vector products behind them run once instead of once per step of every request. The values are those a
// per-step pass computes (the same layers on the same vector).
#pragma once

#include <cstddef>
#include <cstdint>
#include <map>
#include <utility>

#include "backend/backend.h"

namespace tether::models {

template <class Key>
class KeptPerTime {
 public:
  // The array of `size` floats for `key`: kept, or filled now by `fill(Ptr<float>)`. Past kMaxKept keys (a caller
  // sweeping times) the array is filled into one reused buffer instead of being kept.
  template <class Fill>
  backend::Ptr<const float> get(backend::Backend& be, Key key, int64_t size, Fill&& fill) {
    if (const auto kept = kept_.find(key); kept != kept_.end()) return kept->second.at();
    if (kept_.size() >= kMaxKept) {
      if (overflow_.size() < size) overflow_ = be.alloc<float>(size);
      fill(overflow_.at());
      return overflow_.at();
    }
    backend::Array<float> a = be.alloc<float>(size);
    fill(a.at());
    return kept_.emplace(key, std::move(a)).first->second.at();
  }

 private:
  static constexpr std::size_t kMaxKept = 64;
  std::map<Key, backend::Array<float>> kept_;
  backend::Array<float> overflow_;
};

}  // namespace tether::models
