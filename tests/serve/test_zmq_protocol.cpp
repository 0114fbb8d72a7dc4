// Tether's ZMQ protocol: the msgpack form of /act's fields, the envelope (api_key, request_id, id) and the reply map.
#include <gtest/gtest.h>

#include "serve/http_error.h"
#include "serve/zmq_protocol.h"

using namespace tether;
using namespace tether::serve;
namespace mp = tether::serve::msgpack;

namespace {

models::ModelSpec spec() {
  models::ModelSpec s;
  s.family = "smolvla";
  s.cameras = {"observation.images.front", "observation.images.wrist"};
  s.camera_prefix = "observation.images.";
  s.state_dim = 3;
  s.action_dim = 3;
  s.chunk_size = 4;
  return s;
}

void raw_image(mp::Writer& w, int h, int wd, std::size_t bytes) {
  w.map(2);
  w.str("data");
  w.bin(std::string(bytes, '\x40'));
  w.str("shape");
  w.array(3);
  w.integer(h);
  w.integer(wd);
  w.integer(3);
}

// A request; `extra` adds one more entry written by the callback.
std::string message(int state_dim = 3, const char* camera = "front", std::size_t image_bytes = 12,
                    std::function<void(mp::Writer&)> extra = nullptr) {
  mp::Writer w;
  w.map(extra ? 7 : 6);
  w.str("instruction");
  w.str("pick");
  w.str("state");
  w.array(uint32_t(state_dim));
  for (int i = 0; i < state_dim; ++i) w.float32(float(i));
  w.str("images");
  w.map(1);
  w.str(camera);
  raw_image(w, 2, 2, image_bytes);
  w.str("seed");
  w.integer(5);
  w.str("api_key");
  w.str("k");
  w.str("id");
  w.integer(42);
  if (extra) extra(w);
  return w.take();
}

std::string code_of(const std::string& m) {
  try {
    zmqp::decode_message(m, spec());
  } catch (const HttpError& e) {
    EXPECT_EQ(e.status(), 400);
    return e.code() + ": " + e.what();
  }
  return "ok";
}

}  // namespace

TEST(ZmqProtocol, DecodesActFieldsAndEnvelope) {
  const std::string m = message();
  const zmqp::Request req = zmqp::parse_request(m);
  EXPECT_EQ(req.api_key, "k");
  EXPECT_EQ(req.id, Json(42));
  const ActRequest r = zmqp::decode_act(req, spec());
  EXPECT_EQ(r.observation.instruction, "pick");
  EXPECT_EQ(r.observation.state, (std::vector<float>{0, 1, 2}));
  EXPECT_EQ(r.observation.images.at("observation.images.front").rgb.size(), 12u);
  EXPECT_EQ(r.seed, 5u);
}

TEST(ZmqProtocol, Rtc) {
  const std::string m = message(3, "front", 12, [](mp::Writer& w) {
    w.str("rtc");
    w.map(2);
    w.str("prev_actions");
    w.array(2);
    for (int r = 0; r < 2; ++r) {
      w.array(3);
      for (int c = 0; c < 3; ++c) w.float64(r + c);
    }
    w.str("inference_delay");
    w.integer(1);
  });
  const ActRequest r = zmqp::decode_message(m, spec());
  ASSERT_TRUE(r.rtc.has_value());
  EXPECT_EQ(r.rtc->rows, 2);
  EXPECT_EQ(r.rtc->inference_delay, 1);
  EXPECT_EQ(r.rtc->prev_actions.size(), 6u);
}

TEST(ZmqProtocol, Refusals) {
  EXPECT_EQ(code_of("\xc1").substr(0, 11), "bad_msgpack");
  EXPECT_EQ(code_of("\x01").substr(0, 11), "bad_msgpack");
  EXPECT_EQ(code_of(message(2)).substr(0, 13), "invalid_state");
  EXPECT_EQ(code_of(message(3, "top")).substr(0, 14), "unknown_camera");
  EXPECT_NE(code_of(message(3, "front", 11)).find("images.front.data: 11 bytes"), std::string::npos);
  EXPECT_EQ(code_of(message(3, "front", 12, [](mp::Writer& w) {
              w.str("colour");
              w.str("red");
            })).substr(0, 13),
            "unknown_field");
  EXPECT_NE(code_of(message(3, "front", 12, [](mp::Writer& w) {
              w.str("image");
              w.bin("\x89PNG");
            })).find("not both"),
            std::string::npos);
  // PNG bytes that are not a PNG.
  mp::Writer w;
  w.map(3);
  w.str("instruction");
  w.str("x");
  w.str("state");
  w.array(3);
  for (int i = 0; i < 3; ++i) w.integer(i);
  w.str("image");
  w.bin(std::string("\x89PNG\r\n\x1a\n garbage", 17));
  EXPECT_EQ(code_of(w.take()).substr(0, 13), "invalid_image");
}

TEST(ZmqProtocol, ReplyCarriesStatusIdAndFloat32Actions) {
  const Json body = {{"actions", {{1.5, 2.5}, {3.5, 4.5}}}, {"num_actions", 2}, {"request_id", "r1"}};
  const std::string bytes = zmqp::encode_reply(200, body, 1, "r1", Json("abc"));
  const mp::Value v = mp::parse(bytes);
  EXPECT_EQ(v.find("status")->integer, 200);
  EXPECT_EQ(v.find("id")->bytes, "abc");
  EXPECT_EQ(v.find("request_id")->bytes, "r1");
  EXPECT_EQ(v.find("actions")->items.at(1).items.at(0).kind, mp::Kind::float32);
  EXPECT_EQ(v.find("actions")->items.at(1).items.at(0).number, 3.5);

  const std::string err = zmqp::encode_reply(503, {{"error", {{"code", "queue_full"}, {"message", "m"}}}}, 2, "r2", Json());
  const mp::Value e = mp::parse(err);
  EXPECT_EQ(e.find("error")->find("code")->bytes, "queue_full");
  EXPECT_EQ(e.find("retry_after_s")->integer, 2);
  EXPECT_EQ(e.find("request_id")->bytes, "r2");
  EXPECT_EQ(e.find("id"), nullptr);
}

// POST /act with Content-Type: application/msgpack: the same map, without the envelope fields (headers over HTTP).
TEST(ZmqProtocol, HttpBodyHasTheActFieldsOnly) {
  mp::Writer w;
  w.map(4);
  w.str("instruction");
  w.str("pick");
  w.str("state");
  w.array(3);
  for (int i = 0; i < 3; ++i) w.float32(float(i));
  w.str("image");
  raw_image(w, 2, 2, 12);
  w.str("seed");
  w.integer(9);
  const ActRequest r = zmqp::decode_http_body(w.take(), spec());
  EXPECT_EQ(r.observation.instruction, "pick");
  EXPECT_EQ(*r.seed, 9u);
  EXPECT_EQ(r.observation.images.at("observation.images.front").width, 2);

  auto http_code = [](const std::string& body) {
    try {
      zmqp::decode_http_body(body, spec());
    } catch (const HttpError& e) {
      EXPECT_EQ(e.status(), 400);
      return e.code() + ": " + e.what();
    }
    return std::string("ok");
  };
  // message() carries api_key and id: over HTTP they are unknown fields.
  EXPECT_NE(http_code(message()).find("unknown_field: unknown field 'api_key'"), std::string::npos);
  EXPECT_EQ(http_code("").substr(0, 11), "bad_msgpack");
  EXPECT_EQ(http_code("\x93\x01\x02\x03").substr(0, 11), "bad_msgpack");  // an array, not a map
  EXPECT_EQ(http_code(std::string("\x81\xa5state", 7)).substr(0, 11), "bad_msgpack");  // truncated
  mp::Writer wrong;
  wrong.map(3);
  wrong.str("instruction");
  wrong.integer(1);
  wrong.str("state");
  wrong.str("1,2,3");
  wrong.str("image");
  raw_image(wrong, 2, 2, 12);
  EXPECT_EQ(http_code(wrong.take()), "invalid_field: instruction: expected a string, got integer");
}

TEST(ZmqProtocol, HttpAnswerIsTheBodyAsAMap) {
  const Json body = {{"actions", {{1.5, 2.5}}}, {"num_actions", 1}, {"request_id", "r1"}};
  const std::string bytes = zmqp::encode_body(body);  // the parsed value's strings are views into it
  const mp::Value v = mp::parse(bytes);
  EXPECT_EQ(v.entries.size(), 3u);  // nothing added: no status, no id
  EXPECT_EQ(v.find("actions")->items.at(0).items.at(1).kind, mp::Kind::float32);
  EXPECT_EQ(v.find("actions")->items.at(0).items.at(1).number, 2.5);
  EXPECT_EQ(v.find("request_id")->bytes, "r1");
}
