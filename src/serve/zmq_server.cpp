// The ROUTER loop of the ZMQ transports: framing, limits, the reply queue and its wake-up socket.
#include "serve/zmq_server.h"

#include <algorithm>
#include <boost/asio/post.hpp>
#include <cctype>
#include <cstdio>
#include <deque>
#include <fstream>
#include <mutex>
#include <sstream>
#include <vector>
#include <zmq.hpp>

#include "core/error.h"
#include "serve/host_address.h"

namespace tether::serve {

namespace {

// A message's routing frames (the client's identity, and the empty delimiter a REQ socket adds) and its payload.
struct Outgoing {
  std::vector<std::string> envelope;
  std::string payload;
};

// Frames a message may have before it is refused; the rest of a longer one is read and discarded.
constexpr std::size_t kMaxFrames = 8;
// Messages taken from the socket before the reply queue is looked at again.
constexpr int kBatchReceive = 256;

void send_message(zmq::socket_t& socket, const Outgoing& m) {
  // Never blocks: a reply to a peer that is gone, or whose queue is full (ZMQ_SNDHWM), is dropped.
  for (const auto& frame : m.envelope)
    if (!socket.send(zmq::buffer(frame), zmq::send_flags::sndmore | zmq::send_flags::dontwait)) return;
  (void)socket.send(zmq::buffer(m.payload), zmq::send_flags::dontwait);
}

}  // namespace

struct ZmqServer::Shared {
  std::mutex mu;
  std::deque<Outgoing> queue;
  std::unique_ptr<zmq::socket_t> wake_tx;  // under mu; null once the loop has closed
  bool signalled = false;
  std::atomic<int> in_flight{0};
  std::function<std::string(int, const std::string&, const std::string&)> error;

  void push(Outgoing m) {
    std::lock_guard<std::mutex> lock(mu);
    if (!wake_tx) {  // stopped: nobody will send it
      in_flight.fetch_sub(1);
      return;
    }
    queue.push_back(std::move(m));
    if (!signalled) {
      signalled = true;
      (void)wake_tx->send(zmq::str_buffer("w"), zmq::send_flags::dontwait);
    }
  }
};

struct ZmqReply::State {
  std::shared_ptr<ZmqServer::Shared> shared;
  std::vector<std::string> envelope;
  std::atomic<bool> done{false};
  ~State() {
    if (!done.exchange(true))
      shared->push({std::move(envelope), shared->error(500, "internal_error", "the request was dropped unanswered")});
  }
};

void ZmqReply::operator()(std::string payload) const {
  if (state_->done.exchange(true)) return;
  state_->shared->push({std::move(state_->envelope), std::move(payload)});
}

struct ZmqServer::Sockets {
  zmq::context_t context{1};
  zmq::socket_t router{context, zmq::socket_type::router};
  zmq::socket_t wake_rx{context, zmq::socket_type::pair};
};

ZmqServer::ZmqServer(ZmqServerOptions options, ZmqHandler handler, boost::asio::io_context& ioc)
    : opts_(std::move(options)), handler_(std::move(handler)), ioc_(ioc), shared_(std::make_shared<Shared>()) {
  shared_->error = handler_.error;
}

ZmqServer::~ZmqServer() { stop(); }

int ZmqServer::in_flight() const { return shared_->in_flight.load(); }

uint16_t ZmqServer::start() {
  auto s = std::make_unique<Sockets>();
  // libzmq binds numeric addresses (or interface names) only: a name such as "localhost" is resolved here, and every
  // address it has is bound, so a client reaches the socket whichever of them its own lookup picks (a ZMQ client
  // without ZMQ_IPV6 connects over IPv4 only). The first one decides the port; failing to bind it is an error,
  // failing to bind a further one a warning.
  const std::vector<std::string> addresses = resolve_host(opts_.host);
  const auto endpoint = [](const std::string& address, const std::string& port) {
    const bool v6 = address.find(':') != std::string::npos;
    return "tcp://" + (v6 ? "[" + address + "]" : address) + ":" + port;
  };
  const bool any_v6 = std::any_of(addresses.begin(), addresses.end(),
                                  [](const std::string& a) { return a.find(':') != std::string::npos; });
  try {
    s->router.set(zmq::sockopt::linger, 500);  // replies already queued (a kill's answer) still go out on close
    s->router.set(zmq::sockopt::rcvhwm, 10000);
    s->router.set(zmq::sockopt::sndhwm, 10000);
    if (any_v6) s->router.set(zmq::sockopt::ipv6, 1);  // IPv4 addresses still bind with it
    if (opts_.max_message_bytes > 0) s->router.set(zmq::sockopt::maxmsgsize, int64_t(opts_.max_message_bytes));
    if (opts_.curve_secret_z85) {
      s->router.set(zmq::sockopt::curve_server, 1);
      s->router.set(zmq::sockopt::curve_secretkey, *opts_.curve_secret_z85);
    }
    s->router.bind(endpoint(addresses.front(), opts_.port == 0 ? std::string("*") : std::to_string(opts_.port)));
  } catch (const zmq::error_t& e) {
    throw Error(ErrorCode::io, opts_.name + ": cannot listen on " + opts_.host + ":" + std::to_string(opts_.port) +
                                   (addresses.front() == opts_.host ? "" : " (" + addresses.front() + ")") + ": " +
                                   e.what());
  }
  const std::string bound = s->router.get(zmq::sockopt::last_endpoint);
  const uint16_t port = uint16_t(std::stoi(bound.substr(bound.rfind(':') + 1)));
  for (std::size_t i = 1; i < addresses.size(); ++i) {
    try {
      s->router.bind(endpoint(addresses[i], std::to_string(port)));
    } catch (const zmq::error_t& e) {
      std::fprintf(stderr, "tether serve: %s: not also listening on %s (%s), port %u: %s\n", opts_.name.c_str(),
                   addresses[i].c_str(), opts_.host.c_str(), unsigned(port), e.what());
    }
  }

  char address[64];
  std::snprintf(address, sizeof address, "inproc://tether-%s-wake-%p", opts_.name.c_str(), static_cast<void*>(this));
  s->wake_rx.bind(address);
  auto tx = std::make_unique<zmq::socket_t>(s->context, zmq::socket_type::pair);
  tx->set(zmq::sockopt::linger, 0);
  tx->connect(address);
  {
    std::lock_guard<std::mutex> lock(shared_->mu);
    shared_->wake_tx = std::move(tx);
  }
  sockets_ = std::move(s);
  thread_ = std::thread([this] { loop(); });
  return port;
}

void ZmqServer::stop() {
  if (stopping_.exchange(true)) return;
  if (thread_.joinable()) thread_.join();
  std::unique_ptr<Sockets> s = std::move(sockets_);
  {
    std::lock_guard<std::mutex> lock(shared_->mu);
    shared_->wake_tx.reset();
    shared_->in_flight.fetch_sub(int(shared_->queue.size()));
    shared_->queue.clear();
  }
  s.reset();  // closes the sockets (the router lingers briefly), then the context
}

void ZmqServer::loop() {
  Sockets& s = *sockets_;
  auto send_queued = [&] {
    std::deque<Outgoing> batch;
    {
      std::lock_guard<std::mutex> lock(shared_->mu);
      batch.swap(shared_->queue);
      shared_->signalled = false;
    }
    for (const auto& m : batch) {
      send_message(s.router, m);
      shared_->in_flight.fetch_sub(1);
    }
  };
  std::vector<zmq::message_t> frames;
  while (!stopping_.load()) {
    zmq::pollitem_t items[] = {{s.router.handle(), 0, ZMQ_POLLIN, 0}, {s.wake_rx.handle(), 0, ZMQ_POLLIN, 0}};
    try {
      zmq::poll(items, 2, std::chrono::milliseconds(50));
    } catch (const zmq::error_t&) {
      continue;  // EINTR
    }
    if (items[1].revents & ZMQ_POLLIN) {
      zmq::message_t m;
      while (s.wake_rx.recv(m, zmq::recv_flags::dontwait)) {
      }
    }
    send_queued();
    if (!(items[0].revents & ZMQ_POLLIN)) continue;
    for (int n = 0; n < kBatchReceive; ++n) {
      frames.clear();
      std::size_t total = 0;
      bool got = false;
      for (;;) {
        zmq::message_t m;
        if (!s.router.recv(m, zmq::recv_flags::dontwait)) break;
        got = true;
        const bool more = m.more();
        ++total;
        if (frames.size() < kMaxFrames) frames.push_back(std::move(m));
        if (!more) break;
      }
      if (!got) break;
      const auto received = std::chrono::steady_clock::now();
      if (frames.empty()) continue;
      // The envelope: the identity ROUTER prepends, plus everything up to the first empty frame (REQ's delimiter);
      // without an empty frame (a plain DEALER) just the identity.
      Outgoing out;
      std::size_t body = 1;
      for (std::size_t i = 1; i < frames.size(); ++i)
        if (frames[i].size() == 0) {
          body = i + 1;
          break;
        }
      for (std::size_t i = 0; i < body; ++i) out.envelope.push_back(frames[i].to_string());
      const std::size_t body_frames = total - body;
      std::string problem;
      if (body_frames != 1)
        problem = "expected one message frame after the envelope, got " + std::to_string(body_frames);
      else if (frames[body].size() == 0)
        problem = "the message frame is empty";
      if (!problem.empty()) {
        out.payload = handler_.error(400, "bad_frames", problem);
        send_message(s.router, out);
        continue;
      }
      if (draining_.load()) {
        out.payload = handler_.error(503, "shutting_down", "the server is shutting down");
        send_message(s.router, out);
        continue;
      }
      auto state = std::make_shared<ZmqReply::State>();
      state->shared = shared_;
      state->envelope = std::move(out.envelope);
      shared_->in_flight.fetch_add(1);
      boost::asio::post(ioc_, [h = handler_.handle, payload = frames[body].to_string(), received,
                               reply = ZmqReply(std::move(state))]() mutable {
        h(std::move(payload), received, std::move(reply));
      });
    }
    send_queued();
  }
  send_queued();
  s.router.close();
  s.wake_rx.close();
}

std::string curve_public_key(const std::string& secret_z85) {
  if (secret_z85.size() != 40)
    throw Error(ErrorCode::invalid_argument, "a CURVE secret key is 40 Z85 characters, got " + std::to_string(secret_z85.size()));
  char pub[41] = {0};
  if (zmq_curve_public(pub, secret_z85.c_str()) != 0)
    throw Error(ErrorCode::invalid_argument, std::string("not a Z85 CURVE secret key: ") + zmq_strerror(zmq_errno()));
  return pub;
}

std::string read_curve_secret_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(ErrorCode::io, "cannot read the CURVE secret key file " + path);
  std::stringstream ss;
  ss << in.rdbuf();
  std::string key;
  for (char c : ss.str())
    if (!std::isspace(static_cast<unsigned char>(c))) key += c;
  try {
    (void)curve_public_key(key);
  } catch (const Error& e) {
    throw Error(ErrorCode::invalid_argument, path + ": " + e.what());
  }
  return key;
}

}  // namespace tether::serve
