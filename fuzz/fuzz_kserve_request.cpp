// libFuzzer target: any bytes as a KServe v2 infer request yield per-item ActRequests the engine accepts, or an
// HttpError(400) with a contract code, nothing else. The input's first line is the Inference-Header-Content-Length
// header's value (empty: no header), the rest the HTTP body (the JSON header, then any binary tensor data).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "serve/kserve_protocol.h"

namespace {

const tether::models::ModelSpec& spec() {
  static const tether::models::ModelSpec s = [] {
    tether::models::ModelSpec m;
    m.family = "smolvla";
    m.cameras = {"observation.images.front", "observation.images.wrist"};
    m.camera_prefix = "observation.images.";
    m.state_dim = 3;
    m.action_dim = 3;
    m.chunk_size = 4;
    return m;
  }();
  return s;
}

bool known_code(const std::string& c) {
  for (const char* k : {"bad_json", "invalid_field", "invalid_state", "unknown_camera", "unknown_field", "missing_field"})
    if (c == k) return true;
  return false;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace kserve = tether::serve::kserve;
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const std::size_t newline = input.find('\n');
  const std::string_view header = newline == std::string_view::npos ? std::string_view() : input.substr(0, newline);
  const std::string_view body = newline == std::string_view::npos ? input : input.substr(newline + 1);
  try {
    const auto req = kserve::decode_infer_request(body, header, spec());
    if (req.items.empty() || int64_t(req.items.size()) > kserve::kMaxBatchItems || req.outputs.empty()) __builtin_trap();
    std::vector<kserve::ItemAnswer> answers;
    for (const auto& item : req.items) {
      const auto& obs = item.observation;
      if (int64_t(obs.state.size()) != spec().state_dim || obs.images.empty()) __builtin_trap();
      for (float v : obs.state)
        if (!std::isfinite(v)) __builtin_trap();
      for (const auto& [camera, img] : obs.images) {
        if (!tether::serve::resolve_camera(camera, spec())) __builtin_trap();
        if (img.rgb.empty() || img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3) __builtin_trap();
      }
      answers.push_back({std::vector<float>(12, 0.5f), 4, 3, "model"});
    }
    for (const auto& o : req.outputs)
      if (o.name != kserve::kActions && o.name != kserve::kActionSource) __builtin_trap();
    const auto enc = kserve::encode_infer_response("fuzz", req, answers);
    if (enc.header_length && *enc.header_length > enc.body.size()) __builtin_trap();
  } catch (const tether::serve::HttpError& e) {
    if (e.status() != 400 || !known_code(e.code()) || std::strlen(e.what()) == 0) __builtin_trap();
  }
  return 0;
}
