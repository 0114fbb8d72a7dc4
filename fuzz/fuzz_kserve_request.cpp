// libFuzzer target: any bytes as a KServe v2 infer request yield per-item ActRequests the engine accepts, or an
// HttpError(400) with a contract code, nothing else. The input's first line is the Inference-Header-Content-Length
// header's value (empty: no header), the rest the HTTP body (the JSON header, then any binary tensor data).
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "fuzz_spec.h"
#include "serve/kserve_protocol.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace kserve = tether::serve::kserve;
  const std::string_view input(reinterpret_cast<const char*>(data), size);
  const std::size_t newline = input.find('\n');
  const std::string_view header = newline == std::string_view::npos ? std::string_view() : input.substr(0, newline);
  const std::string_view body = newline == std::string_view::npos ? input : input.substr(newline + 1);
  try {
    const auto req = kserve::decode_infer_request(body, header, tether::fuzz::fake_spec());
    if (req.items.empty() || int64_t(req.items.size()) > kserve::kMaxBatchItems || req.outputs.empty()) __builtin_trap();
    std::vector<kserve::ItemAnswer> answers;
    for (const auto& item : req.items) {
      tether::fuzz::check_accepted(item);
      answers.push_back({std::vector<float>(12, 0.5f), 4, 3, "model"});
    }
    for (const auto& o : req.outputs)
      if (o.name != kserve::kActions && o.name != kserve::kActionSource) __builtin_trap();
    const auto enc = kserve::encode_infer_response("fuzz", req, answers);
    if (enc.header_length && *enc.header_length > enc.body.size()) __builtin_trap();
  } catch (const tether::serve::HttpError& e) {
    tether::fuzz::check_refusal(e, {"bad_json", "invalid_field", "invalid_state", "unknown_camera", "unknown_field",
                                    "missing_field"});
  }
  return 0;
}
