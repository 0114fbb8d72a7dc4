// The /act pipeline, independent of any transport: auth, readiness, the body limit, parsing, every safety wedge
// in order (runtime/wedges.h), inference under the deadline, the fallback, the guard, the trace line and the
// metrics. Every transport (HTTP's /act and KServe v2, openpi's WebSocket, GR00T's and Tether's ZMQ) only turns its
// bytes into an ActInput and the ActResponse back into its own reply (serve/transport.h).
#pragma once

#include <boost/asio/any_io_executor.hpp>
#include <boost/asio/awaitable.hpp>
#include <boost/asio/thread_pool.hpp>
#include <chrono>
#include <exception>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include "core/json_util.h"
#include "runtime/fallback_client.h"
#include "serve/act_request.h"
#include "serve/act_trace.h"
#include "serve/metrics.h"
#include "serve/model_host.h"
#include "serve/server_options.h"

namespace tether::serve {

// What a transport knows about a request besides its body.
struct RequestContext {
  std::string request_id;  // chosen by the transport (the client's when valid, else request_id_or_new's)
  std::string api_key;     // the key the client presented, however its transport carries it; empty: none
  std::chrono::steady_clock::time_point received;  // when the request's first bytes were read: deadlines start here
  // Forwarded by another server's fallback client (runtime::kFallbackMarkerHeader): answered locally, never
  // forwarded again.
  bool from_fallback = false;
  // The way in, as metrics and traces name it: http, kserve, openpi, gr00t or zmq.
  std::string transport = "http";
  // The endpoint label tether_requests_total counts the answer under (KServe: "/v2/models/{name}/infer").
  std::string endpoint = "/act";
};

// A request as a transport hands it over. Decoding waits until auth and readiness have passed (the model's cameras
// and sizes are known only then); it throws HttpError(400, code) naming the field at fault, as parse_act_request does.
struct ActInput {
  std::size_t wire_bytes = 0;  // checked against --max-body-bytes before anything is decoded
  std::function<ActRequest(const models::ModelSpec&)> decode;
  // The request as a POST /act body, for the cloud fallback (which speaks /act); HTTP passes its body as is, other
  // transports re-encode what they decoded (act_request_json).
  std::function<std::string(const ActRequest&)> act_json;
  // The embodiment tag the request names (serve/model_host.h's ModelHosts routes by it), read after auth and before
  // decoding; null or empty: the server's default. A wire format that cannot be read yields empty here and its error
  // from `decode`.
  std::function<std::string()> embodiment = {};
};

// A request its transport refused while decoding its wire format, before it could become ActInputs of its own (a body
// that is not JSON, a bad binary header): the pipeline refuses it at its decoding step with `error`, so it is counted
// and leaves a trace line naming its transport, as a request whose ActInput::decode throws does.
ActInput refused_input(std::size_t wire_bytes, std::exception_ptr error);

// The answer in transport-neutral form. HTTP sends `status` as the status line and `body` as JSON, with
// Retry-After: `retry_after_s` on a 503.
struct ActResponse {
  int status = 200;
  Json body;              // the /act answer, or {"error": {"code", "message"}} (see error_body)
  int retry_after_s = 1;  // meaningful with 503
  bool ok() const { return status == 200; }
};

class ActPipeline {
 public:
  ActPipeline(const ServerOptions& options, ModelHosts& hosts, Metrics& metrics);
  ~ActPipeline();
  ActPipeline(const ActPipeline&) = delete;
  ActPipeline& operator=(const ActPipeline&) = delete;

  // Runs one request to its answer; never throws. Counts it in tether_requests_total{transport, endpoint} (ctx's).
  // `input` and `ctx` must outlive the awaitable (await it at once). Awaits the batcher and the fallback without
  // blocking the calling executor's thread.
  boost::asio::awaitable<ActResponse> run(const ActInput& input, const RequestContext& ctx);
  // An /act JSON body (HTTP's POST /act).
  boost::asio::awaitable<ActResponse> run(std::string_view body, const RequestContext& ctx);

 private:
  struct Act;
  struct InferenceWait;
  struct Inference;

  boost::asio::awaitable<ActResponse> traced(const ActInput& input, const RequestContext& ctx, ModelHost& host);
  boost::asio::awaitable<ActResponse> answer(const ActInput& input, const RequestContext& ctx, ModelHost& host,
                                             ActTrace& trace);
  Act parse(const ActInput& input, const RequestContext& ctx, ModelHost& host, ActTrace& trace);
  boost::asio::awaitable<void> admit(Act& a, const RequestContext& ctx);
  void try_skip(Act& a);
  boost::asio::awaitable<Inference> infer(Act& a, const RequestContext& ctx);
  boost::asio::awaitable<void> recover(Act& a, Inference& inference, const RequestContext& ctx,
                                       ActTrace& trace);
  ActResponse respond(Act& a, const RequestContext& ctx, ActTrace& trace);

  std::shared_ptr<InferenceWait> start_inference(const boost::asio::any_io_executor& ex, Act& a,
                                                 runtime::Clock::time_point observed,
                                                 runtime::Clock::time_point batch_deadline);
  boost::asio::awaitable<void> call_fallback(Act& a, const std::string& request_id);

  const ServerOptions& opts_;
  ModelHosts& hosts_;
  Metrics& metrics_;
  std::unique_ptr<runtime::FallbackClient> fallback_;  // null without --cloud-fallback
  // Fallback calls block in libcurl: they run here, never on an I/O thread. Declared last: joined first.
  std::unique_ptr<boost::asio::thread_pool> fallback_pool_;
};

}  // namespace tether::serve
