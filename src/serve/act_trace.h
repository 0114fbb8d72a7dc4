// One /act request's trace line: what it learned as the pipeline advanced, written (hash-chained) by the
// recorder whether the request succeeded or not.
#pragma once

#include <string>

#include "core/json_util.h"
#include "policy/policy.h"
#include "runtime/wedges.h"
#include "serve/engine.h"
#include "serve/metrics.h"
#include "serve/model_host.h"

namespace tether::serve {

// Filled as the pipeline advances; fields never reached stay null.
struct ActTrace {
  std::string episode_id, task, transport;
  Json inputs, actions, latency = Json::object(), wedges = Json::object();
  bool has_episode = false;
};

// Inputs of a request as the trace keeps them: images by hash unless `images_full` (--record-images full), then
// also in the raw-image form /act accepts, so a recorded request can be replayed as it was.
Json trace_inputs(const policy::Observation& obs, bool images_full);

// Appends the line to the host's recorder when --record is on; a failed write is counted, never thrown.
// `status`: the response's; `code`/`message`: the error's (empty on success).
void record_trace(ModelHost& host, Metrics& metrics, const ActTrace& trace,
                  const std::string& request_id, int status, const std::string& code, const std::string& message);

}  // namespace tether::serve
