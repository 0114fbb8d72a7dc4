// The ZMQ side shared by the GR00T and Tether ZMQ transports: one thread owns a ROUTER socket (libzmq sockets are not
// thread-safe and libzmq is not Asio), hands each message to a handler on the server's I/O threads, and sends the
// replies those handlers queue. A ROUTER serves many clients (REQ or DEALER) at once, so their requests batch.
#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <thread>

#include <boost/asio/io_context.hpp>

namespace tether::serve {

// Answers one request; thread-safe, the first call wins. Dropping every copy without calling it answers with the
// handler's internal-error reply, so a client waiting on a REQ socket is never left hanging.
class ZmqReply {
 public:
  struct State;  // public for the server's own use
  explicit ZmqReply(std::shared_ptr<State> s) : state_(std::move(s)) {}
  void operator()(std::string payload) const;

 private:
  std::shared_ptr<State> state_;
};

struct ZmqServerOptions {
  std::string name;  // the transport's name, for messages
  std::string host;
  uint16_t port = 0;  // 0: a free one
  std::size_t max_message_bytes = 0;  // ZMQ_MAXMSGSIZE: libzmq drops a peer that sends a larger frame; 0: no limit
  std::optional<std::string> curve_secret_z85;  // CURVE server with this secret key; absent: plain TCP
};

struct ZmqHandler {
  // A request's payload (the one frame after the envelope). Called on an I/O thread; it must call `reply` exactly once,
  // from any thread, when the answer is ready. `received`: when the message was read.
  std::function<void(std::string payload, std::chrono::steady_clock::time_point received, ZmqReply reply)> handle;
  // A reply the server sends on its own: framing errors (400), draining (503), a handler that never answered (500).
  std::function<std::string(int status, const std::string& code, const std::string& message)> error;
};

class ZmqServer {
 public:
  ZmqServer(ZmqServerOptions options, ZmqHandler handler, boost::asio::io_context& ioc);
  ~ZmqServer();
  ZmqServer(const ZmqServer&) = delete;
  ZmqServer& operator=(const ZmqServer&) = delete;

  // Binds (throws tether::Error(io) naming the address) and starts the socket thread; returns the bound port.
  uint16_t start();
  void begin_draining() { draining_ = true; }
  int in_flight() const;
  void stop();

  struct Shared;  // the reply queue, shared with ZmqReply

 private:
  struct Sockets;
  void loop();

  ZmqServerOptions opts_;
  ZmqHandler handler_;
  boost::asio::io_context& ioc_;
  std::shared_ptr<Shared> shared_;  // what replies outliving this object may still touch
  std::unique_ptr<Sockets> sockets_;  // owned by the loop thread while it runs
  std::atomic<bool> draining_{false}, stopping_{false};
  std::thread thread_;
};

// The Z85 public key of a Z85 CURVE secret key (zmq_curve_public); throws tether::Error(invalid_argument).
std::string curve_public_key(const std::string& secret_z85);
// A CURVE secret key read from a file (40 Z85 characters, surrounding whitespace ignored); throws naming the file.
std::string read_curve_secret_file(const std::string& path);

}  // namespace tether::serve
