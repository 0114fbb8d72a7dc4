// Rehearsing failures on a healthy model: a synthetic delay before every forward pass (--inject-latency-ms) and a
// file whose presence makes every forward pass throw (--inject-failure-file).
#pragma once

#include <string>

#include "runtime/batcher.h"

namespace tether::runtime {

// `predict` wrapped so that each call first sleeps `latency_ms` (when > 0), then throws tether::Error(internal)
// while `failure_file` exists (when not empty). With neither set, `predict` itself.
PredictFn with_injected_faults(PredictFn predict, double latency_ms, const std::string& failure_file);

}  // namespace tether::runtime
