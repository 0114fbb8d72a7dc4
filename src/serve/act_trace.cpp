// Building and appending the trace line of an /act request.
#include "serve/act_trace.h"

#include "core/hash.h"
#include "serve/base64.h"
#include "serve/wedge_metrics.h"

namespace tether::serve {

Json trace_inputs(const policy::Observation& obs, bool images_full) {
  Json images = Json::object();
  for (const auto& [camera, img] : obs.images) {
    Json i = {{"width", img.width}, {"height", img.height},
              {"sha256", sha256_hex(std::string(img.rgb.begin(), img.rgb.end()))}};
    if (images_full)
      i["data"] = {{"data", base64_encode(img.rgb.data(), img.rgb.size())}, {"shape", {img.height, img.width, 3}}};
    images[camera] = std::move(i);
  }
  return {{"state", obs.state}, {"images", std::move(images)}, {"seed", obs.seed}};
}

void record_trace(ModelHost& host, Metrics& metrics, const ActTrace& t, const std::string& request_id, int status,
                  const std::string& code, const std::string& message) {
  runtime::TraceRecorder* rec = host.wedges().recorder();
  if (!rec) return;
  const Engine& engine = host.engine();
  Json line = {{"request_id", request_id},
               {"episode_id", t.has_episode ? Json(t.episode_id) : Json(nullptr)},
               {"task", t.task},
               {"transport", t.transport.empty() ? Json(nullptr) : Json(t.transport)},
               {"model", engine.model_name},
               {"model_hash", engine.model_hash},
               {"embodiment", engine.spec.embodiment.empty() ? Json(nullptr) : Json(engine.spec.embodiment)},
               {"status", status == 200 ? "success" : "failed"},
               {"http_status", status},
               {"error", code.empty() ? Json(nullptr) : Json{{"code", code}, {"message", message}}},
               {"inputs", t.inputs.is_null() ? Json(nullptr) : t.inputs},
               {"actions", t.actions.is_null() ? Json(nullptr) : t.actions},
               {"latency_ms", t.latency},
               {"wedges", t.wedges}};
  if (!rec->append(std::move(line))) count_wedge_event(metrics, WedgeEvent::trace_write_error, host.metric_labels());
}

}  // namespace tether::serve
