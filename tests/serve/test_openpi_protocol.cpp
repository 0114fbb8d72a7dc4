// openpi frames to ActRequests through each layout, the mapping file, the errors and their keys, and the reply map as
// openpi_client's msgpack-numpy reads it.
#include <gtest/gtest.h>

#include <cstring>
#include <fstream>
#include <functional>

#include "serve/http_error.h"
#include "serve/msgpack.h"
#include "serve/openpi_protocol.h"

using namespace tether;
using namespace tether::serve;
namespace mp = tether::serve::msgpack;

namespace {

models::ModelSpec spec(std::vector<std::string> cameras = {"observation.images.front"}, int64_t state_dim = 6) {
  models::ModelSpec s;
  s.family = "smolvla";
  s.cameras = std::move(cameras);
  s.camera_prefix = "observation.images.";
  s.state_dim = state_dim;
  s.action_dim = 6;
  s.chunk_size = 4;
  s.stages = {"vision", "denoise"};
  return s;
}

// A msgpack map built entry by entry: each entry writes its key and value.
using Entry = std::function<void(mp::Writer&)>;

std::string map_of(const std::vector<Entry>& entries) {
  mp::Writer w;
  w.map(uint32_t(entries.size()));
  for (const auto& e : entries) e(w);
  return w.take();
}

// An array as msgpack-numpy writes it (binary keys), or with string keys.
void ndarray(mp::Writer& w, const std::string& dtype, std::vector<int64_t> shape, std::string_view data,
             bool bin_keys = true) {
  auto key = [&](std::string_view k) { bin_keys ? w.bin(k) : w.str(k); };
  w.map(4);
  key("__ndarray__");
  w.boolean(true);
  key("data");
  w.bin(data);
  key("dtype");
  w.str(dtype);
  key("shape");
  w.array(uint32_t(shape.size()));
  for (auto d : shape) w.integer(d);
}

template <typename T>
std::string bytes_of(const std::vector<T>& v) {
  return std::string(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
}

std::vector<uint8_t> pixels(int h, int w, int c = 3) {
  std::vector<uint8_t> px(std::size_t(h) * w * c);
  for (std::size_t i = 0; i < px.size(); ++i) px[i] = uint8_t(i * 7 + 1);
  return px;
}

Entry image_entry(const std::string& key, int h = 4, int w = 5, bool bin_keys = true) {
  return [=](mp::Writer& wr) {
    wr.str(key);
    ndarray(wr, "|u1", {h, w, 3}, bytes_of(pixels(h, w)), bin_keys);
  };
}

Entry state_entry(const std::string& key, std::vector<double> values) {
  return [=](mp::Writer& w) {
    w.str(key);
    ndarray(w, "<f8", {int64_t(values.size())}, bytes_of(values));
  };
}

Entry text_entry(const std::string& key, const std::string& value) {
  return [=](mp::Writer& w) {
    w.str(key);
    w.str(value);
  };
}

std::vector<double> six() { return {0.5, -1, 2, 3, 4, 5}; }

std::string libero_frame(bool bin_keys = true) {
  return map_of({image_entry("observation/image", 4, 5, bin_keys), image_entry("observation/wrist_image", 4, 5, bin_keys),
                 state_entry("observation/state", six()), text_entry("prompt", "pick up the cube")});
}

openpi::Layouts layouts(const std::string& name) { return openpi::load_layouts(name); }

void expect_error(const std::string& frame, const openpi::Layouts& l, const models::ModelSpec& s,
                  const std::string& code, const std::string& mention) {
  try {
    openpi::decode_request(frame, l, s);
    ADD_FAILURE() << "accepted";
  } catch (const HttpError& e) {
    EXPECT_EQ(e.status(), 400);
    EXPECT_EQ(e.code(), code) << e.what();
    EXPECT_NE(std::string(e.what()).find(mention), std::string::npos) << e.what();
  }
}

}  // namespace

TEST(OpenpiDecode, LiberoFrameFeedsTheFirstCameraAndIgnoresTheWristTheModelLacks) {
  for (bool bin_keys : {true, false}) {
    const ActRequest req = openpi::decode_request(libero_frame(bin_keys), layouts("libero"), spec());
    const auto& obs = req.observation;
    ASSERT_EQ(obs.images.size(), 1u);
    const auto& img = obs.images.at("observation.images.front");
    EXPECT_EQ(img.height, 4);
    EXPECT_EQ(img.width, 5);
    EXPECT_EQ(img.rgb, pixels(4, 5));
    EXPECT_EQ(obs.state, (std::vector<float>{0.5f, -1, 2, 3, 4, 5}));
    EXPECT_EQ(obs.instruction, "pick up the cube");
    EXPECT_FALSE(req.seed);
    EXPECT_FALSE(req.episode_id);
  }
}

TEST(OpenpiDecode, CamerasGoByNameFirstThenByPosition) {
  // "wrist_image" is a camera of this model: the wrist key goes there by name, the base key takes what is left.
  const auto s = spec({"observation.images.top", "observation.images.wrist_image"});
  const auto req = openpi::decode_request(libero_frame(), layouts("libero"), s);
  EXPECT_EQ(req.observation.images.size(), 2u);
  const auto cams = openpi::resolve_cameras(layouts("libero").candidates[0], s);
  ASSERT_EQ(cams.size(), 2u);
  EXPECT_EQ(cams[0], "observation.images.top");
  EXPECT_EQ(cams[1], "observation.images.wrist_image");
  // Synthetic cameras are never fed by a client.
  auto with_synthetic = spec({"observation.images.empty_camera_0", "observation.images.front"});
  with_synthetic.synthetic_cameras = {"observation.images.empty_camera_0"};
  const auto c2 = openpi::resolve_cameras(layouts("libero").candidates[0], with_synthetic);
  EXPECT_EQ(c2[0], "observation.images.front");
  EXPECT_FALSE(c2[1]);
}

TEST(OpenpiDecode, DroidConcatenatesJointsAndAScalarGripper) {
  const std::vector<double> joints = {1, 2, 3, 4, 5};
  for (int form = 0; form < 3; ++form) {
    Entry gripper = [form](mp::Writer& w) {
      w.str("observation/gripper_position");
      if (form == 0) {  // a 0-d array
        const std::vector<double> g = {0.25};
        ndarray(w, "<f8", {}, bytes_of(g));
      } else if (form == 1) {  // np.float64(0.25): a numpy scalar
        w.map(3);
        w.bin(std::string_view("__npgeneric__"));
        w.boolean(true);
        w.bin(std::string_view("data"));
        w.float64(0.25);
        w.bin(std::string_view("dtype"));
        w.str("<f8");
      } else {  // a plain float
        w.float64(0.25);
      }
    };
    const auto frame = map_of({image_entry("observation/exterior_image_1_left"), image_entry("observation/wrist_image_left"),
                               state_entry("observation/joint_position", joints), gripper, text_entry("prompt", "go")});
    for (const char* name : {"droid", "auto"}) {
      const auto req = openpi::decode_request(frame, layouts(name), spec());
      EXPECT_EQ(req.observation.state, (std::vector<float>{1, 2, 3, 4, 5, 0.25f})) << name << form;
      EXPECT_EQ(req.observation.images.count("observation.images.front"), 1u);
    }
  }
}

TEST(OpenpiDecode, AlohaNestedChannelsFirstImagesAreTransposed) {
  const int h = 2, w = 3;
  std::vector<uint8_t> chw(3 * h * w);
  for (int c = 0; c < 3; ++c)
    for (int i = 0; i < h * w; ++i) chw[std::size_t(c * h * w + i)] = uint8_t(c * 100 + i);
  const auto frame = map_of({[&](mp::Writer& wr) {
                               wr.str("images");
                               wr.map(2);
                               wr.str("cam_high");
                               ndarray(wr, "|u1", {3, h, w}, bytes_of(chw));
                               wr.str("cam_low");
                               ndarray(wr, "|u1", {3, h, w}, bytes_of(chw));
                             },
                             state_entry("state", six()), text_entry("prompt", "fold")});
  const auto s = spec({"observation.images.cam_high", "observation.images.cam_left_wrist"});
  for (const char* name : {"aloha", "auto"}) {
    const auto req = openpi::decode_request(frame, layouts(name), s);
    ASSERT_EQ(req.observation.images.size(), 1u) << name;  // cam_low: no camera left for it
    const auto& img = req.observation.images.at("observation.images.cam_high");
    ASSERT_EQ(img.height, h);
    ASSERT_EQ(img.width, w);
    for (int px = 0; px < h * w; ++px)
      for (int c = 0; c < 3; ++c) EXPECT_EQ(img.rgb[std::size_t(px * 3 + c)], c * 100 + px);
  }
}

TEST(OpenpiDecode, FloatImagesAreScaledAndTruncatedAsOpenpiDoes) {
  const std::vector<float> f = {0.0f, 0.5f, 1.0f, 0.999f, 0.1f, 0.2f};  // [1, 2, 3]
  auto frame = [&](std::vector<float> values) {
    return map_of({[values](mp::Writer& w) {
                     w.str("observation/image");
                     ndarray(w, "<f4", {1, 2, 3}, bytes_of(values));
                   },
                   state_entry("observation/state", six()), text_entry("prompt", "x")});
  };
  const auto req = openpi::decode_request(frame(f), layouts("libero"), spec());
  const auto& rgb = req.observation.images.at("observation.images.front").rgb;
  for (std::size_t i = 0; i < f.size(); ++i) EXPECT_EQ(rgb[i], uint8_t(255.0f * f[i])) << i;
  expect_error(frame({0, 0, 0, 1.5f, 0, 0}), layouts("libero"), spec(), "invalid_image", "[0, 1]");
}

TEST(OpenpiDecode, RefusesObjectAndUnknownDtypesNamingTheKey) {
  for (const char* dtype : {"|O", "<U4", "<c8", "|V8", "float32"}) {
    const auto frame = map_of({[dtype](mp::Writer& w) {
                                 w.str("observation/image");
                                 ndarray(w, dtype, {1, 1, 3}, std::string(std::strlen(dtype) == 0 ? 0 : 8, 'x'));
                               },
                               state_entry("observation/state", six()), text_entry("prompt", "x")});
    expect_error(frame, layouts("libero"), spec(), "invalid_field", "observation/image");
  }
  // An int64 image is a number array but not pixels.
  const std::vector<int64_t> ints(3, 1);
  const auto frame = map_of({[&](mp::Writer& w) {
                               w.str("observation/image");
                               ndarray(w, "<i8", {1, 1, 3}, bytes_of(ints));
                             },
                             state_entry("observation/state", six()), text_entry("prompt", "x")});
  expect_error(frame, layouts("libero"), spec(), "invalid_image", "int64");
}

TEST(OpenpiDecode, ErrorsNameTheKeyAtFault) {
  const auto l = layouts("libero");
  expect_error(map_of({image_entry("observation/image"), state_entry("observation/state", six()),
                       text_entry("prompt", "x"), text_entry("observation/extra", "?")}),
               l, spec(), "unknown_field", "observation/extra");
  expect_error(map_of({image_entry("observation/image"), text_entry("prompt", "x")}), l, spec(), "missing_field",
               "observation/state");
  expect_error(map_of({image_entry("observation/image"), state_entry("observation/state", {1, 2})}), l, spec(),
               "missing_field", "prompt");
  expect_error(map_of({image_entry("observation/image"), state_entry("observation/state", {1, 2}),
                       text_entry("prompt", "x")}),
               l, spec(), "invalid_state", "6");
  expect_error(map_of({state_entry("observation/state", six()), text_entry("prompt", "x")}), l, spec(),
               "missing_field", "image");
  expect_error(map_of({image_entry("observation/image", 0, 5), state_entry("observation/state", six()),
                       text_entry("prompt", "x")}),
               l, spec(), "invalid_image", "observation/image");
  expect_error(map_of({text_entry("observation/image", "png?"), state_entry("observation/state", six()),
                       text_entry("prompt", "x")}),
               l, spec(), "invalid_image", "observation/image");
  expect_error(std::string("\x81\xa3key", 5), l, spec(), "invalid_msgpack", "msgpack");
  expect_error(std::string("\x93\x01\x02\x03", 4), l, spec(), "invalid_field", "map");
  // The auto layout names the layout closest to what was sent.
  expect_error(map_of({image_entry("observation/image"), state_entry("observation/state", six()),
                       text_entry("prompt", "x"), text_entry("wat", "?")}),
               layouts("auto"), spec(), "unknown_field", "libero");
}

TEST(OpenpiDecode, EpisodeAndSeedExtensions) {
  const auto frame = map_of({image_entry("observation/image"), state_entry("observation/state", six()),
                             text_entry("prompt", "x"), text_entry("episode_id", "ep-1"), [](mp::Writer& w) {
                               w.str("seed");
                               w.integer(42);
                             }});
  const auto req = openpi::decode_request(frame, layouts("libero"), spec());
  EXPECT_EQ(req.episode_id, "ep-1");
  EXPECT_EQ(req.seed, 42u);
}

TEST(OpenpiLayoutFile, MapsKeysStateAndPrompt) {
  const auto l = openpi::parse_layout_json(R"({
    "images": {"cam/main": "front", "cam/aux": "observation.images.side"},
    "state": ["arm", "hand"], "prompt": "task", "default_prompt": "tidy up", "ignore": ["debug"]})",
                                           "my.json");
  openpi::Layouts ls{"my.json", {l}};
  const auto s = spec({"observation.images.front", "observation.images.side"});
  const auto frame = map_of({image_entry("cam/main"), state_entry("arm", {1, 2, 3}), state_entry("hand", {4, 5, 6}),
                             text_entry("debug", "ignored")});
  const auto req = openpi::decode_request(frame, ls, s);
  EXPECT_EQ(req.observation.instruction, "tidy up");
  EXPECT_EQ(req.observation.state, (std::vector<float>{1, 2, 3, 4, 5, 6}));
  EXPECT_EQ(req.observation.images.count("observation.images.front"), 1u);
  // A mapping file's camera the model lacks is an error, not ignored.
  expect_error(frame, ls, spec(), "unknown_camera", "my.json");
}

TEST(OpenpiLayoutFile, RefusesTyposAndDoubleRoles) {
  auto refuses = [](const std::string& text, const std::string& mention) {
    try {
      openpi::parse_layout_json(text, "f.json");
      ADD_FAILURE() << text;
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(mention), std::string::npos) << e.what();
    }
  };
  refuses(R"({"images": {"a": "front"}, "state": "s", "promt": "p"})", "promt");
  refuses(R"({"images": {"a": "front"}, "state": ["a"]})", "'a'");
  refuses(R"({"images": {}, "state": "s"})", "images");
  refuses(R"({"images": {"a": "front"}})", "state");
  refuses(R"({"images": {"a": 3}, "state": "s"})", "images.a");
  refuses("[1]", "object");
  refuses("{", "JSON");
  EXPECT_THROW(openpi::load_layouts("/nonexistent/layout.json"), Error);
  EXPECT_EQ(openpi::load_layouts("auto").candidates.size(), 3u);
}

TEST(OpenpiReply, ActionsAsMsgpackNumpyAndOpenpiTimings) {
  const Json body = {{"actions", {{1.0, 2.0}, {3.0, 4.5}, {5.0, 6.0}}},
                     {"num_actions", 3},
                     {"action_dim", 2},
                     {"latency_ms", {{"total", 9.0}, {"queue", 1.0}, {"vision", 2.0}, {"denoise", 3.5}, {"predict", 6.0}}},
                     {"request_id", "r-1"}};
  for (bool first : {true, false}) {
    openpi::ServerTiming timing{7.5, first ? std::nullopt : std::optional<double>(20.0)};
    const std::string out = openpi::encode_reply(body, timing);
    const mp::Value v = mp::parse(out);
    ASSERT_TRUE(v.is_map());
    const mp::Value* actions = v.find("actions");
    ASSERT_TRUE(actions);
    // Binary keys, as msgpack-numpy writes them (its unpackb looks up b"__ndarray__").
    ASSERT_EQ(actions->entries.size(), 4u);
    EXPECT_TRUE(actions->entries[0].first.is_bin());
    EXPECT_EQ(actions->entries[0].first.bytes, "__ndarray__");
    EXPECT_EQ(actions->find("dtype")->bytes, "<f4");
    const mp::Value* shape = actions->find("shape");
    ASSERT_EQ(shape->items.size(), 2u);
    EXPECT_EQ(shape->items[0].integer, 3);
    EXPECT_EQ(shape->items[1].integer, 2);
    const std::string_view data = actions->find("data")->bytes;
    ASSERT_EQ(data.size(), 6 * sizeof(float));
    float values[6];
    std::memcpy(values, data.data(), sizeof values);
    EXPECT_EQ(values[3], 4.5f);
    EXPECT_DOUBLE_EQ(v.find("policy_timing")->find("infer_ms")->as_double(), 6.0);
    const mp::Value* server = v.find("server_timing");
    EXPECT_DOUBLE_EQ(server->find("infer_ms")->as_double(), 7.5);
    EXPECT_EQ(server->find("prev_total_ms") == nullptr, first);
    EXPECT_EQ(v.find("tether")->find("request_id")->bytes, "r-1");
    EXPECT_FALSE(v.find("tether")->find("actions"));
  }
}

TEST(OpenpiReply, JsonBecomesMsgpack) {
  const Json j = {{"a", nullptr}, {"b", true}, {"c", -3}, {"d", 2.5}, {"e", {1, "x"}}, {"f", {{"g", 1u}}}};
  const std::string bytes = openpi::encode_json(j);  // the parsed values are views into it
  const mp::Value v = mp::parse(bytes);
  EXPECT_TRUE(v.find("a")->is_nil());
  EXPECT_TRUE(v.find("b")->boolean);
  EXPECT_EQ(v.find("c")->integer, -3);
  EXPECT_DOUBLE_EQ(v.find("d")->number, 2.5);
  EXPECT_EQ(v.find("e")->items[1].bytes, "x");
  EXPECT_EQ(v.find("f")->find("g")->integer, 1);
}

// The fuzz seeds (fuzz/seeds/openpi_request/) are valid frames, so the fuzzer starts from accepted inputs.
TEST(OpenpiDecode, FuzzSeedsAreAccepted) {
  const auto s = spec({"observation.images.front", "observation.images.wrist"}, 3);
  openpi::Layouts file{"fuzz.json", {openpi::parse_layout_json(
                                        R"({"images": {"cam/a": "front", "cam/b": "wrist"}, "state": ["s1", "s2"],
                                            "prompt": "task", "default_prompt": "go", "ignore": ["x"]})",
                                        "fuzz.json")}};
  const std::string dir = std::string(TETHER_SOURCE_DIR) + "/fuzz/seeds/openpi_request/";
  int n = 0;
  for (const char* name : {"libero", "droid_scalar_gripper", "aloha_nested_chw", "float_image", "file_layout",
                           "str_keys"}) {
    std::ifstream in(dir + name + ".msgpack", std::ios::binary);
    const std::string bytes((std::istreambuf_iterator<char>(in)), {});
    ASSERT_FALSE(bytes.empty()) << name;
    const auto& l = (bytes[0] & 1) ? file : layouts("auto");
    EXPECT_NO_THROW(openpi::decode_request(std::string_view(bytes).substr(1), l, s)) << name;
    ++n;
  }
  EXPECT_EQ(n, 6);
}

TEST(OpenpiDecode, AFrameOfManySmallElementsIsRefusedEarly) {
  mp::Writer w;
  w.map(1);
  w.str("observation/state");
  w.array(100000);
  for (int i = 0; i < 100000; ++i) w.nil();
  expect_error(w.take(), layouts("libero"), spec(), "invalid_msgpack", "array items");
}
