// Tether's ZMQ transport: each message is one pipeline run; the reply carries the client's id back.
#include "serve/zmq_transport.h"

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/detached.hpp>
#include <cstdio>

#include "serve/request_id.h"
#include "serve/zmq_protocol.h"
#include "serve/zmq_server.h"

namespace tether::serve {

namespace {

namespace net = boost::asio;

struct Exchange {
  std::string payload;  // the Request's views point into it
  zmqp::Request request;
  ActInput input;
  RequestContext context;
  ZmqReply reply;
  explicit Exchange(ZmqReply r) : reply(std::move(r)) {}
};

net::awaitable<void> run_exchange(std::shared_ptr<Exchange> x, ActPipeline* pipeline) {
  const ActResponse r = co_await pipeline->run(x->input, x->context);
  x->reply(zmqp::encode_reply(r.status, r.body, r.retry_after_s, x->context.request_id, x->request.id));
}

ZmqServerOptions server_options(const ServerOptions& o) {
  ZmqServerOptions z{"zmq", o.host, *o.zmq_port, o.zmq_max_message_bytes, std::nullopt};
  if (!o.zmq_curve_secret_file.empty()) z.curve_secret_z85 = read_curve_secret_file(o.zmq_curve_secret_file);
  return z;
}

class ZmqTransport final : public Transport {
 public:
  explicit ZmqTransport(const TransportContext& ctx)
      : ctx_(ctx),
        server_(server_options(ctx.options),
                {[this](std::string payload, std::chrono::steady_clock::time_point received, ZmqReply reply) {
                   handle(std::move(payload), received, std::move(reply));
                 },
                 &zmqp::error_reply},
                ctx.ioc) {}

  const char* name() const override { return "zmq"; }
  uint16_t start() override {
    const uint16_t port = server_.start();
    if (!ctx_.options.zmq_curve_secret_file.empty())
      std::fprintf(stderr, "tether serve: zmq CURVE public key %s\n",
                   curve_public_key(read_curve_secret_file(ctx_.options.zmq_curve_secret_file)).c_str());
    return port;
  }
  void begin_draining() override { server_.begin_draining(); }
  int in_flight() const override { return server_.in_flight(); }
  void stop() override { server_.stop(); }

 private:
  void handle(std::string payload, std::chrono::steady_clock::time_point received, ZmqReply reply) {
    auto x = std::make_shared<Exchange>(std::move(reply));
    x->payload = std::move(payload);
    Exchange* raw = x.get();
    try {
      x->request = zmqp::parse_request(x->payload);
      x->input.wire_bytes = x->payload.size();
      x->input.decode = [raw](const models::ModelSpec& spec) { return zmqp::decode_act(raw->request, spec); };
      x->input.act_json = [](const ActRequest& r) { return act_request_json(r); };
      x->input.embodiment = [raw] { return zmqp::embodiment_of(raw->request.root); };
    } catch (...) {
      // Not even the envelope reads (not msgpack, not a map): every message is an /act request, so the pipeline
      // refuses this one at its decoding step and it is counted and traced like any other (after the API key check:
      // a message whose key cannot be read is answered 401 when the server has one).
      x->input = refused_input(x->payload.size(), std::current_exception());
    }
    x->context.request_id = request_id_or_new({x->request.request_id});
    x->context.api_key = x->request.api_key;
    x->context.received = received;
    x->context.transport = "zmq";
    net::co_spawn(ctx_.ioc, run_exchange(x, &ctx_.pipeline), net::detached);
  }

  TransportContext ctx_;
  ZmqServer server_;
};

}  // namespace

std::unique_ptr<Transport> make_zmq_transport(const TransportContext& ctx) { return std::make_unique<ZmqTransport>(ctx); }

}  // namespace tether::serve
