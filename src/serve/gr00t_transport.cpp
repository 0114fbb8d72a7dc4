// GR00T's ZMQ transport: endpoint dispatch, one pipeline run per batch item (run at once, so they batch), and the
// reply assembled when the last item is answered.
#include "serve/gr00t_transport.h"

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/detached.hpp>

#include "serve/auth.h"
#include "serve/gr00t_protocol.h"
#include "serve/http_error.h"
#include "serve/request_id.h"
#include "serve/zmq_server.h"

namespace tether::serve {

namespace {

namespace net = boost::asio;

// Batch items per get_action call: beyond the scheduler's queue anyway; a hostile B never spawns more.
constexpr int64_t kMaxItems = 1024;

struct GetAction {
  std::string payload;  // the Call's views point into it
  gr00t::Call call;
  gr00t::Layout layout;
  const ModelHost* host = nullptr;
  std::vector<ActInput> inputs;
  std::vector<RequestContext> contexts;
  std::vector<ActResponse> responses;
  std::atomic<int64_t> remaining{0};
  ZmqReply reply;
  explicit GetAction(ZmqReply r) : reply(std::move(r)) {}
};

std::string error_of(const ActResponse& r, int64_t index, int64_t batch) {
  const Json& e = r.body.contains("error") ? r.body["error"] : Json::object();
  const std::string code = e.value("code", std::string("internal_error"));
  std::string message = e.value("message", std::string("request failed"));
  if (batch > 1) message = "batch item " + std::to_string(index) + ": " + message;
  return gr00t::error_reply(r.status, code, message);
}

void finish(GetAction& g) {
  const int64_t batch = int64_t(g.responses.size());
  for (int64_t i = 0; i < batch; ++i)
    if (!g.responses[std::size_t(i)].ok()) return g.reply(error_of(g.responses[std::size_t(i)], i, batch));
  const Json& first = g.responses.front().body;
  const int64_t rows = first.value("num_actions", int64_t(0)), dim = first.value("action_dim", int64_t(0));
  std::vector<float> actions;
  actions.reserve(std::size_t(batch * rows * dim));
  Json items = Json::array();
  for (auto& r : g.responses) {
    const Json& rows_json = r.body["actions"];
    if (int64_t(rows_json.size()) != rows || r.body.value("action_dim", int64_t(0)) != dim)
      return g.reply(gr00t::error_reply(500, "internal_error", "batch items answered with different chunk shapes"));
    for (const auto& row : rows_json)
      for (const auto& v : row) actions.push_back(v.get<float>());
    Json item = r.body;
    item.erase("actions");
    items.push_back(std::move(item));
  }
  // Items answered: the model is loaded.
  const auto groups = models::answered_action_groups(g.host->engine().spec, dim);
  g.reply(gr00t::action_reply(groups, g.layout.flat, batch, rows, dim, actions, items));
}

net::awaitable<void> run_item(std::shared_ptr<GetAction> g, ActPipeline* pipeline, std::size_t i) {
  g->responses[i] = co_await pipeline->run(g->inputs[i], g->contexts[i]);
  if (g->remaining.fetch_sub(1) == 1) finish(*g);
}

class Gr00tTransport final : public Transport {
 public:
  explicit Gr00tTransport(const TransportContext& ctx)
      : ctx_(ctx),
        server_({"gr00t", ctx.options.host, *ctx.options.gr00t_port, ctx.options.gr00t_max_message_bytes, std::nullopt},
                {[this](std::string payload, std::chrono::steady_clock::time_point received, ZmqReply reply) {
                   handle(std::move(payload), received, std::move(reply));
                 },
                 &gr00t::error_reply},
                ctx.ioc) {}

  const char* name() const override { return "gr00t"; }
  uint16_t start() override { return server_.start(); }
  void begin_draining() override { server_.begin_draining(); }
  int in_flight() const override { return server_.in_flight(); }
  void stop() override { server_.stop(); }

 private:
  void handle(std::string payload, std::chrono::steady_clock::time_point received, ZmqReply reply) {
    auto g = std::make_shared<GetAction>(std::move(reply));
    g->payload = std::move(payload);
    g->host = &ctx_.hosts.primary();
    try {
      g->call = gr00t::parse_call(g->payload);
    } catch (...) {
      // Not even a call (not msgpack, not a map, no known endpoint): the pipeline refuses it at its decoding step, so
      // it is counted and traced under gr00t like any refused request (after the key check: a message whose token
      // cannot be read is answered 401 when the server has a key).
      const std::size_t wire_bytes = g->payload.size();
      g->inputs.push_back(refused_input(wire_bytes, std::current_exception()));
      return run(std::move(g), received);
    }
    try {
      if (g->call.endpoint != gr00t::Endpoint::get_action) return g->reply(other_endpoint(g->call));
    } catch (const HttpError& e) {
      return g->reply(gr00t::error_reply(e.status(), e.code(), e.what()));
    } catch (const std::exception& e) {
      return g->reply(gr00t::error_reply(500, "internal_error", e.what()));
    }
    g->layout = gr00t::observation_layout(g->call);
    const int64_t batch = g->layout.batch;
    if (batch > kMaxItems)
      return g->reply(gr00t::error_reply(400, "invalid_field", "observation: a batch of " + std::to_string(batch) +
                                                                   " items; at most " + std::to_string(kMaxItems)));
    g->inputs.resize(std::size_t(batch));
    // The embodiment the call is for: the pipeline routes each item there (an unknown tag is its 400), and the reply
    // is split into that embodiment's action groups. A tag that is not a string is decode_item's 400.
    std::string tag;
    try {
      tag = gr00t::call_embodiment(g->call);
      g->host = &ctx_.hosts.route(tag);
    } catch (const std::exception&) {
    }
    GetAction* raw = g.get();
    for (int64_t i = 0; i < batch; ++i) {
      auto& input = g->inputs[std::size_t(i)];
      input.wire_bytes = g->payload.size();
      input.decode = [raw, i](const models::ModelSpec& spec) { return gr00t::decode_item(raw->call, i, spec); };
      input.act_json = [](const ActRequest& r) { return act_request_json(r); };
      input.embodiment = [tag] { return tag; };
    }
    run(std::move(g), received);
  }

  // Runs g's inputs through the pipeline at once (so they batch); the reply goes when the last one has answered.
  void run(std::shared_ptr<GetAction> g, std::chrono::steady_clock::time_point received) {
    const std::size_t n = g->inputs.size();
    g->contexts.resize(n);
    g->responses.resize(n);
    g->remaining = int64_t(n);
    for (auto& c : g->contexts) {
      c.request_id = generate_request_id();
      c.api_key = g->call.api_token;
      c.received = received;
      c.transport = "gr00t";
    }
    for (std::size_t i = 0; i < n; ++i) net::co_spawn(ctx_.ioc, run_item(g, &ctx_.pipeline, i), net::detached);
  }

  std::string other_endpoint(const gr00t::Call& call) {
    // Upstream checks the token before any endpoint, ping included.
    check_api_key(call.api_token, ctx_.options.api_key);
    switch (call.endpoint) {
      case gr00t::Endpoint::ping: return gr00t::ping_reply();
      case gr00t::Endpoint::reset: {
        // The episode's last good chunk, guard history and skip cache go: its next get_action starts afresh. Without
        // a tag, in every embodiment served (an episode id names one robot's episode, wherever it ran).
        const std::string tag = gr00t::call_embodiment(call);
        const std::vector<std::string> ids = gr00t::reset_episodes(call);
        std::vector<ModelHost*> hosts;
        if (!tag.empty()) hosts.push_back(&ctx_.hosts.route(tag));  // an unknown tag is refused
        else
          for (std::size_t h = 0; h < ctx_.hosts.size(); ++h) hosts.push_back(&ctx_.hosts[h]);
        for (ModelHost* host : hosts)
          for (const std::string& id : ids) host->wedges().episodes().end(id);
        return gr00t::reset_reply();
      }
      case gr00t::Endpoint::get_modality_config: {
        ModelHost& host = ctx_.hosts.route(gr00t::call_embodiment(call));
        if (!host.serving())
          throw HttpError(503, "not_ready", std::string("the model is not ready (") + health_state_name(host.health()) + ")");
        return gr00t::modality_config_reply(host.engine().spec, host.wedges().action_dim());
      }
      case gr00t::Endpoint::kill:
        if (!ctx_.options.gr00t_allow_kill)
          throw HttpError(403, "kill_disabled", "the kill endpoint is disabled on this server (start it with --gr00t-allow-kill)");
        if (ctx_.request_shutdown) ctx_.request_shutdown();
        return gr00t::kill_reply();
      case gr00t::Endpoint::get_action: break;
    }
    throw HttpError(500, "internal_error", "unhandled endpoint");
  }

  TransportContext ctx_;
  ZmqServer server_;
};

}  // namespace

std::unique_ptr<Transport> make_gr00t_transport(const TransportContext& ctx) {
  return std::make_unique<Gr00tTransport>(ctx);
}

}  // namespace tether::serve
