// KServe / Triton Open Inference Protocol v2 on the HTTP port: GET /v2, /v2/health/live, /v2/health/ready,
// /v2/models/{name}[/versions/1][/ready], POST /v2/models/{name}[/versions/1]/infer. An infer request of B items
// becomes B ActPipeline requests awaited together (so they batch in the scheduler); everything else a request goes
// through (the API key, readiness, limits, the wedges, traces, metrics) is the pipeline's, with transport "kserve".
#pragma once

#include <boost/asio/awaitable.hpp>
#include <chrono>
#include <memory>
#include <string>
#include <string_view>

#include "serve/act_pipeline.h"
#include "serve/http_message.h"
#include "serve/metrics.h"
#include "serve/model_host.h"
#include "serve/server_options.h"

namespace tether::serve {

// True for /v2 and the paths below it: the Router hands them to KServeEndpoints.
bool is_kserve_path(std::string_view target);
// The endpoint label of tether_requests_total for a /v2 target ("/v2/models/{name}/infer", ..., or "other").
std::string kserve_endpoint_label(std::string_view target);
// The protocol's error form {"error": message}; a 503 carries Retry-After: `retry_after_s`.
HttpResponse kserve_error_response(const HttpRequest& req, int status, const std::string& message,
                                   const std::string& request_id, int retry_after_s = 1);

class KServeEndpoints {
 public:
  KServeEndpoints(const ServerOptions& options, ModelHosts& hosts, Metrics& metrics, ActPipeline& pipeline);

  // Answers one /v2 request and counts it (transport "kserve"); never throws. Runs on the connection's strand (or
  // any single-threaded executor): the batch items' pipeline requests are spawned on the same executor.
  boost::asio::awaitable<HttpResponse> handle(const HttpRequest& req, const std::string& request_id,
                                              std::chrono::steady_clock::time_point received);

  // The name the model is served under: --model-name, else the checkpoint directory's name.
  std::string model_name() const;

 private:
  struct Prepared;
  // The GET endpoints' answers; throws HttpError.
  HttpResponse get(const HttpRequest& req, const std::string& request_id);
  // An infer request up to its items (method, model, key, readiness, decoding) into `out`, whose items the inputs
  // point to; throws HttpError before decoding. A request refused while decoding becomes one input that the pipeline
  // refuses (refused_input), so it is traced.
  void prepare(const HttpRequest& req, const std::string& request_id, std::chrono::steady_clock::time_point received,
               Prepared& out);
  // Runs the items through the pipeline, which counts each; never throws.
  boost::asio::awaitable<HttpResponse> run_items(const HttpRequest& req, const std::string& request_id,
                                                 Prepared& p);

  const ServerOptions& opts_;
  ModelHosts& hosts_;
  Metrics& metrics_;
  ActPipeline& pipeline_;
};

}  // namespace tether::serve
