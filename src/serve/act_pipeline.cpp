// The /act pipeline in wedge order: circuit breaker -> similarity skip -> inference under the deadline -> cloud
// fallback -> last good chunk -> action guard -> response, trace line and metrics.
#include "serve/act_pipeline.h"

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/redirect_error.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <cmath>
#include <cstdio>
#include <optional>

#include "serve/act_request.h"
#include "serve/auth.h"
#include "serve/http_error.h"
#include "serve/request_id.h"
#include "serve/wedge_metrics.h"

namespace tether::serve {

namespace net = boost::asio;
using runtime::BatchError;
using Clock = runtime::Clock;

namespace {

double ms_since(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

bool all_finite(const std::vector<float>& v) {
  for (float x : v)
    if (!std::isfinite(x)) return false;
  return true;
}

std::string format_ms(double ms) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g ms", ms);
  return buf;
}

ActResponse error_response(int status, const std::string& code, const std::string& message, int retry_after_s = 1) {
  return {status, error_body(code, message), retry_after_s};
}

}  // namespace

// One request as it advances through the wedges.
struct ActPipeline::Act {
  ModelHost* host = nullptr;  // the embodiment's (ModelHosts::route)
  ActRequest parsed;
  double parse_ms = 0;
  std::shared_ptr<runtime::Episode> ep;
  std::vector<float> state;             // as the client sent it (robot units)
  std::vector<float> normalized_state;  // only for the similarity skip
  runtime::WedgeReport report;
  std::optional<std::vector<float>> actions;  // set by the first wedge that answers
  int64_t rows = 0;
  std::optional<runtime::BatchResult> ran;  // set when this request's own forward pass answered
  bool may_forward = false;                 // the fallback may be called for this request
  std::string fallback_body;                // with may_forward: the request as /act JSON, taken before inference
  bool probe = false;                       // this request is the circuit's half-open probe
};

// Local inference as one request waits for it: completed on the request's executor, or abandoned at the deadline
// (the forward pass then still finishes and refreshes the episode's last good chunk).
struct ActPipeline::InferenceWait {
  explicit InferenceWait(const net::any_io_executor& ex) : timer(ex) {}
  net::steady_timer timer;
  bool done = false;
  std::exception_ptr error;
  runtime::BatchResult result;
};

// How step 3 ended when it gave no actions.
struct ActPipeline::Inference {
  std::shared_ptr<InferenceWait> wait;
  std::optional<BatchError::Kind> failure;
  std::string failure_message;
  bool has_deadline = false;
};

ActInput refused_input(std::size_t wire_bytes, std::exception_ptr error) {
  return {wire_bytes, [error](const models::ModelSpec&) -> ActRequest { std::rethrow_exception(error); },
          [](const ActRequest& r) { return act_request_json(r); }};
}

ActPipeline::ActPipeline(const ServerOptions& options, ModelHosts& hosts, Metrics& metrics)
    : opts_(options), hosts_(hosts), metrics_(metrics) {
  const auto& w = opts_.wedges;
  if (!w.cloud_fallback.empty()) {
    fallback_ = std::make_unique<runtime::FallbackClient>(w.cloud_fallback, w.fallback_timeout_ms, w.fallback_api_key);
    fallback_pool_ = std::make_unique<net::thread_pool>(2);
  }
}

ActPipeline::~ActPipeline() = default;

net::awaitable<ActResponse> ActPipeline::run(const ActInput& input, const RequestContext& ctx) {
  ActResponse res;
  try {
    check_api_key(ctx.api_key, opts_.api_key);
    ModelHost& host = hosts_.route(input.embodiment ? input.embodiment() : std::string());
    if (!host.serving())
      throw HttpError(503, "not_ready",
                      std::string("the model is not ready (") + health_state_name(host.health()) + ")");
    // HTTP enforces this while reading; a transport that hands over a whole message relies on this check.
    if (input.wire_bytes > opts_.max_body_bytes)
      throw HttpError(413, "body_too_large",
                      "the request exceeds " + std::to_string(opts_.max_body_bytes) + " bytes (--max-body-bytes)");
    res = co_await traced(input, ctx, host);
  } catch (const HttpError& e) {
    res = error_response(e.status(), e.code(), e.what(), e.retry_after_s());
  } catch (const std::exception& e) {
    res = error_response(500, "internal_error", std::string("internal error: ") + e.what());
  } catch (...) {
    res = error_response(500, "internal_error", "internal error");
  }
  metrics_.count_request(ctx.endpoint, res.status, ctx.transport);
  co_return res;
}

net::awaitable<ActResponse> ActPipeline::run(std::string_view body, const RequestContext& ctx) {
  const ActInput input{body.size(), [body](const models::ModelSpec& spec) { return parse_act_request(body, spec); },
                       [body](const ActRequest&) { return std::string(body); },
                       [body] { return act_request_embodiment(body); }};
  co_return co_await run(input, ctx);
}

// Every request that passed auth and readiness leaves one trace line, whatever its outcome.
net::awaitable<ActResponse> ActPipeline::traced(const ActInput& input, const RequestContext& ctx, ModelHost& host) {
  ActTrace trace;
  trace.transport = ctx.transport;  // also on a request whose decoding fails
  try {
    ActResponse res = co_await answer(input, ctx, host, trace);
    record_trace(host, metrics_, trace, ctx.request_id, 200, "", "");
    co_return res;
  } catch (const HttpError& e) {
    trace.latency["total"] = ms_since(ctx.received);
    record_trace(host, metrics_, trace, ctx.request_id, e.status(), e.code(), e.what());
    throw;
  } catch (const std::exception& e) {
    trace.latency["total"] = ms_since(ctx.received);
    record_trace(host, metrics_, trace, ctx.request_id, 500, "internal_error",
                 std::string("internal error: ") + e.what());
    throw;
  }
}

net::awaitable<ActResponse> ActPipeline::answer(const ActInput& input, const RequestContext& ctx, ModelHost& host,
                                                ActTrace& trace) {
  Act a = parse(input, ctx, host, trace);
  co_await admit(a, ctx);  // 1. circuit breaker
  try_skip(a);                   // 2. similarity skip
  if (!a.actions) {              // 3. inference under the deadline
    Inference inference = co_await infer(a, ctx);
    if (inference.failure) co_await recover(a, inference, ctx, trace);  // 4. fallback, 5. last good chunk
  }
  co_return respond(a, ctx, trace);  // 7. guard, then the answer
}

ActPipeline::Act ActPipeline::parse(const ActInput& input, const RequestContext& ctx, ModelHost& host,
                                    ActTrace& trace) {
  const auto& w = opts_.wedges;
  const Engine& engine = host.engine();
  auto& wedges = host.wedges();
  const auto t_parse = Clock::now();
  Act a;
  a.host = &host;
  trace.transport = ctx.transport;  // before decoding: a request refused there is traced with its transport too
  a.parsed = input.decode(engine.spec);
  policy::Observation& obs = a.parsed.observation;
  obs.seed = a.parsed.seed ? *a.parsed.seed : seed_from_request_id(ctx.request_id);
  trace.task = obs.instruction;
  trace.has_episode = a.parsed.episode_id.has_value();
  trace.episode_id = a.parsed.episode_id.value_or("");
  if (wedges.recorder()) trace.inputs = trace_inputs(obs, w.record_images_full);
  if (a.parsed.rtc && !w.sampler.rtc)
    throw HttpError(400, "invalid_field", "rtc: this server runs without --rtc (real-time chunking is off)");
  if (a.parsed.rtc && engine.spec.rtc_refused_for_relative())
    throw HttpError(400, "invalid_field",
                    "rtc: this policy predicts actions relative to the state, so a previous chunk's leftover does "
                    "not carry over; real-time chunking is off for it");
  a.parse_ms = ms_since(t_parse);

  a.ep = wedges.episodes().get(trace.episode_id);
  a.state = obs.state;
  // Only the similarity skip measures in normalised units: nothing to compute without it.
  if (wedges.skip_enabled())
    a.normalized_state = engine.normalize_state ? engine.normalize_state(a.state) : a.state;
  a.rows = engine.spec.chunk_size;
  a.may_forward = fallback_ && !ctx.from_fallback;
  // Inference takes the observation over: what the fallback is sent is fixed now.
  if (a.may_forward) a.fallback_body = input.act_json(a.parsed);
  return a;
}

net::awaitable<void> ActPipeline::admit(Act& a, const RequestContext& ctx) {
  auto& breaker = a.host->wedges().breaker();
  const auto admission = breaker.admit();
  a.probe = admission == runtime::CircuitBreaker::Admission::probe;
  if (admission != runtime::CircuitBreaker::Admission::reject) co_return;
  count_wedge_event(metrics_, WedgeEvent::circuit_rejected, a.host->metric_labels());
  if (a.may_forward) co_await call_fallback(a, ctx.request_id);
  if (!a.actions) {
    const int retry = breaker.retry_after_s();
    throw HttpError(503, "circuit_open",
                    "local inference failed " + std::to_string(opts_.wedges.max_consecutive_crashes) +
                        " times in a row; the circuit is open (a probe request is let through in " +
                        std::to_string(retry) + " s)" +
                        (a.report.fallback_error.empty() ? "" : "; " + a.report.fallback_error),
                    retry);
  }
}

void ActPipeline::try_skip(Act& a) {
  if (a.actions) return;
  auto& wedges = a.host->wedges();
  a.actions = wedges.try_skip(*a.ep, a.parsed.observation, a.normalized_state, a.report);
  // A request answered from the cache tells nothing about the model: the probe goes to a later one.
  if (a.actions && a.probe) {
    wedges.breaker().abandon_probe();
    a.probe = false;
  }
}

net::awaitable<ActPipeline::Inference> ActPipeline::infer(Act& a, const RequestContext& ctx) {
  const auto& w = opts_.wedges;
  policy::Observation& obs = a.parsed.observation;
  obs.adaptive_threshold = w.sampler.adaptive_threshold;
  if (a.parsed.rtc) {
    policy::Observation::Rtc rtc;
    rtc.prev_actions = std::move(a.parsed.rtc->prev_actions);
    // The leftover is what this server answered: back from the embodiment's range to the model's output first.
    a.host->wedges().unmap_output(rtc.prev_actions);
    rtc.inference_delay = a.parsed.rtc->inference_delay;
    rtc.execution_horizon = w.sampler.rtc_execution_horizon;
    rtc.max_guidance_weight = w.sampler.rtc_max_guidance_weight;
    rtc.schedule = w.sampler.rtc_schedule;
    obs.rtc = std::move(rtc);
    a.report.rtc_applied = true;
  }
  Inference inf;
  inf.has_deadline = w.deadline_ms > 0;
  const auto deadline = inf.has_deadline ? ctx.received + std::chrono::microseconds(int64_t(w.deadline_ms * 1000))
                                         : Clock::time_point::max();
  const auto batch_deadline = std::min(deadline, ctx.received + std::chrono::milliseconds(opts_.request_timeout_ms));
  const auto ex = co_await net::this_coro::executor;
  inf.wait = start_inference(ex, a, ctx.received, batch_deadline);
  auto& wait = *inf.wait;
  if (!wait.done) {
    wait.timer.expires_at(deadline);
    boost::system::error_code ec;
    co_await wait.timer.async_wait(net::redirect_error(net::use_awaitable, ec));
  }
  if (!wait.done) {
    inf.failure = BatchError::Kind::deadline_exceeded;
  } else if (wait.error) {
    try {
      std::rethrow_exception(wait.error);
    } catch (const BatchError& e) {
      inf.failure = e.kind();
      inf.failure_message = e.what();
    } catch (const std::exception& e) {
      inf.failure = BatchError::Kind::inference_failed;
      inf.failure_message = e.what();
    }
  } else if (!all_finite(wait.result.chunk.actions)) {
    inf.failure = BatchError::Kind::inference_failed;
    inf.failure_message = "the model produced non-finite actions (NaN or Inf)";
  } else {
    a.ran = std::move(wait.result);
    a.actions = a.ran->chunk.actions;  // already mapped to the embodiment's range by on_model_chunk
    a.report.denoise_steps_used = a.ran->chunk.denoise_steps_used;
  }
  co_return inf;
}

net::awaitable<void> ActPipeline::recover(Act& a, Inference& inf, const RequestContext& ctx,
                                          ActTrace& trace) {
  auto& wedges = a.host->wedges();
  const bool missed = *inf.failure == BatchError::Kind::deadline_exceeded && inf.has_deadline;
  a.report.deadline_exceeded = missed;
  if (missed) count_wedge_event(metrics_, WedgeEvent::deadline_exceeded, a.host->metric_labels());
  if (!missed) a.report.inference_error = inf.failure_message;
  // 4. Cloud fallback, 5. last good chunk.
  if (a.may_forward) co_await call_fallback(a, ctx.request_id);
  if (a.actions) wedges.on_fallback_chunk(*a.ep, *a.actions, a.rows, ctx.received);
  if (!a.actions && missed) a.actions = wedges.last_good(*a.ep, a.report);
  // A non-finite chunk with nothing better to send: the guard replaces each bad value with the last safe command.
  InferenceWait& wait = *inf.wait;
  if (!a.actions && wait.done && !wait.error && wedges.guard_enabled()) {
    a.ran = std::move(wait.result);
    a.actions = a.ran->chunk.actions;
    wedges.map_output(*a.actions);
    a.report.denoise_steps_used = a.ran->chunk.denoise_steps_used;
  }
  if (a.actions) co_return;
  trace.wedges = wedges.response_fields(a.report);
  const std::string tail = a.report.fallback_error.empty() ? "" : "; " + a.report.fallback_error;
  const std::string& message = inf.failure_message;
  switch (*inf.failure) {
    case BatchError::Kind::queue_full: throw HttpError(503, "queue_full", message + tail);
    case BatchError::Kind::stopped: throw HttpError(503, "not_ready", message + tail);
    case BatchError::Kind::inference_failed: throw HttpError(500, "inference_failed", message + tail);
    case BatchError::Kind::deadline_exceeded:
      if (missed)
        throw HttpError(504, "deadline_exceeded",
                        "inference did not finish within --deadline-ms " + format_ms(opts_.wedges.deadline_ms) +
                            " and this episode has no earlier chunk to fall back on" + tail);
      throw HttpError(408, "request_timeout", message + tail);
  }
}

ActResponse ActPipeline::respond(Act& a, const RequestContext& ctx, ActTrace& trace) {
  auto& wedges = a.host->wedges();
  const Engine& engine = a.host->engine();
  // 7. Guard: last, whatever produced the actions.
  wedges.guard(*a.ep, *a.actions, a.rows, a.state, ctx.request_id, trace.episode_id, a.report);
  count_wedge_report(metrics_, a.report, a.host->metric_labels());

  const int64_t dim = wedges.action_dim();  // the model's action_dim, or the embodiment's joints it was cut to
  const auto& actions = *a.actions;
  Json actions_json = Json::array();
  for (int64_t row = 0; row < a.rows; ++row)
    actions_json.push_back(std::vector<float>(actions.begin() + row * dim, actions.begin() + (row + 1) * dim));
  Json latency = Json::object();
  std::vector<std::pair<std::string, double>> stages = {{"total", ms_since(ctx.received)}};
  const auto& ran = a.ran;
  if (ran) {
    stages.emplace_back("queue", ran->queue_ms);
    // The model's stages in its order (ModelSpec::stages); the first also carries parsing and normalisation.
    const auto& names = engine.spec.stages;
    for (std::size_t i = 0; i < names.size(); ++i)
      stages.emplace_back(names[i], ran->timings.get(names[i]) + (i == 0 ? a.parse_ms + ran->normalize_ms : 0.0));
    stages.emplace_back("postprocess", ran->postprocess_ms);
    if (ran->index_in_batch == 0) metrics_.observe_batch_size(ran->batch_size);
  }
  for (const auto& [name, ms] : stages) {
    latency[name] = ms;
    metrics_.observe_stage(name, ms / 1000.0);
  }
  // The policy's whole forward pass for this request's batch, as `tether bench` times it (the stages above plus what
  // lies between them): `total` minus this is what the transport, the queue and the wedges added to the request.
  if (ran) latency["predict"] = ran->predict_ms;
  Json body = {{"actions", actions_json},
               {"num_actions", a.rows},
               {"action_dim", dim},
               {"latency_ms", latency},
               {"inference_mode", inference_mode_json(engine)},
               {"model_hash", engine.model_hash},
               {"request_id", ctx.request_id},
               {"episode_id", a.parsed.episode_id ? Json(*a.parsed.episode_id) : Json(nullptr)},
               {"batch_size", ran ? ran->batch_size : 0},
               {"warnings", ran ? ran->chunk.warnings : std::vector<std::string>{}}};
  const Json wedge_fields = wedges.response_fields(a.report);
  for (auto it = wedge_fields.begin(); it != wedge_fields.end(); ++it) body[it.key()] = it.value();
  trace.actions = std::move(actions_json);
  trace.latency = std::move(latency);
  trace.wedges = wedge_fields;
  return {200, std::move(body), 1};
}

std::shared_ptr<ActPipeline::InferenceWait> ActPipeline::start_inference(const net::any_io_executor& ex, Act& a,
                                                                         Clock::time_point observed,
                                                                         Clock::time_point batch_deadline) {
  auto wait = std::make_shared<InferenceWait>(ex);
  runtime::Wedges* wedges = &a.host->wedges();  // outlives the batcher; this completion may outlive the request
  // The similarity skip compares later observations with this one: keep it when that wedge is on.
  std::shared_ptr<policy::Observation> reference;
  if (wedges->skip_enabled()) reference = std::make_shared<policy::Observation>(a.parsed.observation);
  auto done = [wedges, ex, wait, ep = a.ep, observed, reference, state = a.normalized_state, probe = a.probe](
                  std::exception_ptr e, runtime::BatchResult r) {
    if (!e && !all_finite(r.chunk.actions)) {
      wedges->breaker().record_failure();  // a broken model, even though it did not throw
    } else if (!e) {
      wedges->breaker().record_success();
      wedges->on_model_chunk(*ep, r.chunk.actions, observed, reference.get(), state);
    } else {
      bool model_failed = false;
      try {
        std::rethrow_exception(e);
      } catch (const BatchError& be) {
        model_failed = be.kind() == BatchError::Kind::inference_failed;
      } catch (...) {
        model_failed = true;
      }
      if (model_failed) wedges->breaker().record_failure();
      else if (probe) wedges->breaker().abandon_probe();
    }
    net::post(ex, [wait, e = std::move(e), r = std::move(r)]() mutable {
      wait->done = true;
      wait->error = std::move(e);
      wait->result = std::move(r);
      wait->timer.cancel();
    });
  };
  try {
    a.host->batcher().submit(std::move(a.parsed.observation), batch_deadline, done);
  } catch (...) {
    done(std::current_exception(), runtime::BatchResult{});
  }
  return wait;
}

// Forwards the request body to the fallback server; on success the actions it answered with become the request's.
net::awaitable<void> ActPipeline::call_fallback(Act& a, const std::string& request_id) {
  // The blocking libcurl call runs on the fallback pool; co_spawn brings the result back to this coroutine's strand.
  // The awaitable is a named local: GCC 12 can destroy temporaries of a co_await operand twice.
  struct Call {
    const runtime::FallbackClient* client;
    std::string body, request_id;
    int64_t action_dim;
  };
  auto call = std::make_shared<const Call>(
      Call{fallback_.get(), a.fallback_body, request_id, a.host->wedges().action_dim()});
  auto perform = net::co_spawn(
      *fallback_pool_,
      [call]() -> net::awaitable<runtime::FallbackReply> {
        co_return call->client->call(call->body, call->request_id, call->action_dim);
      },
      net::use_awaitable);
  runtime::FallbackReply reply = co_await std::move(perform);
  if (!reply.actions) {
    a.report.fallback_error = std::move(reply.error);
    count_wedge_event(metrics_, WedgeEvent::fallback_failure, a.host->metric_labels());
    co_return;
  }
  a.actions = std::move(reply.actions);
  a.rows = reply.rows;
  a.report.fallback_used = true;
  a.report.source = runtime::ActionSource::fallback;
  count_wedge_event(metrics_, WedgeEvent::fallback_success, a.host->metric_labels());
}

}  // namespace tether::serve
