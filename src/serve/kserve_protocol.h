// The KServe / Triton Open Inference Protocol v2 as pure functions: an infer request (its JSON header and Triton's
// binary tensor tail) decoded into one ActRequest per batch item, the answer encoded back (JSON or binary tensors),
// and the model's and server's metadata. No sockets and no pipeline here (serve/kserve_endpoints.h serves them;
// fuzz/fuzz_kserve_request.cpp drives the decoder).
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/json_util.h"
#include "models/model.h"
#include "serve/act_request.h"

namespace tether::serve::kserve {

// The tensors the model takes and gives.
inline constexpr const char* kInstruction = "instruction";  // BYTES [B] or [B, 1]
inline constexpr const char* kState = "state";              // FP32 [B, state_dim]
inline constexpr const char* kImagePrefix = "image.";       // image.<camera>: UINT8 [B, H, W, 3]
inline constexpr const char* kSeed = "seed";                // INT64 or UINT64 [B] (or [B, 1]), optional
inline constexpr const char* kEpisodeId = "episode_id";     // BYTES [B] (or [B, 1]), optional
inline constexpr const char* kActions = "actions";          // FP32 [B, chunk, action_dim]
inline constexpr const char* kActionSource = "action_source";  // BYTES [B]: model, cache, fallback, last_good

// The one model version a server holds: what metadata lists and what /versions/{v} accepts.
inline constexpr const char* kModelVersion = "1";
// The extensions GET /v2 lists.
inline constexpr const char* kBinaryExtension = "binary_tensor_data";
// More items than this in one request: 400 (each item becomes one pipeline request).
inline constexpr int64_t kMaxBatchItems = 1024;

// An output the client asked for, in the order the answer lists it.
struct RequestedOutput {
  std::string name;     // kActions or kActionSource
  bool binary = false;  // answered as binary tensor data after the JSON header
};

struct InferRequest {
  std::optional<std::string> id;        // echoed in the answer
  std::vector<ActRequest> items;        // one per batch row, each already checked with check_observation
  std::vector<RequestedOutput> outputs;  // never empty: none requested means every output
  std::string embodiment;  // parameters.embodiment_tag: the GR00T embodiment asked for (empty: the server's default)
};

// Decodes an inference request. `header_length` is the Inference-Header-Content-Length header's value ("" when the
// request has none: the whole body is the JSON header). Throws HttpError(400, code) naming the tensor (or the item) at
// fault; code one of bad_json, invalid_field, invalid_state, unknown_field, unknown_camera, missing_field.
InferRequest decode_infer_request(std::string_view body, std::string_view header_length,
                                  const models::ModelSpec& spec);
// The same for a server of several embodiments: the items are decoded against spec_for(parameters.embodiment_tag)
// (empty: the default), which throws for a tag not served.
using SpecFor = std::function<const models::ModelSpec&(const std::string& embodiment)>;
InferRequest decode_infer_request(std::string_view body, std::string_view header_length, const SpecFor& spec_for);

// One item's answer as the pipeline gave it.
struct ItemAnswer {
  std::vector<float> actions;  // rows * dim, row-major
  int64_t rows = 0, dim = 0;
  std::string action_source = "model";
  // The item's /act latency_ms total and predict (see docs/serve-api.md); the response's parameters carry the largest.
  double total_ms = 0, predict_ms = 0;
};

struct EncodedResponse {
  std::string body;
  // With binary outputs: the JSON header's length (the response's Inference-Header-Content-Length); else none.
  std::optional<std::size_t> header_length;
};

// The inference response for `req`'s requested outputs. Throws HttpError(500, internal_error) when the items'
// chunks differ in shape (a fallback server answering another chunk length), which no single tensor can hold.
EncodedResponse encode_infer_response(const std::string& model_name, const InferRequest& req,
                                      const std::vector<ItemAnswer>& items);

// The input tensor name of a camera: "image." + the key without spec.camera_prefix.
std::string image_tensor_name(const std::string& camera, const models::ModelSpec& spec);

// GET /v2/models/{name}: inputs and outputs with datatypes and shapes (-1 for variable dimensions).
Json model_metadata(const std::string& name, const models::ModelSpec& spec, int64_t action_dim);
// GET /v2: {"name", "version", "extensions"}.
Json server_metadata(const std::string& version);
// The protocol's error object: {"error": message}.
Json error_json(const std::string& message);

}  // namespace tether::serve::kserve
