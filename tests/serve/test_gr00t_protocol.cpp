// GR00T's ZMQ protocol decoding and replies: both observation layouts, batches and histories, state and action split
// into the model's groups, every refusal naming its field, and replies in the shapes upstream's PolicyClient reads.
#include <gtest/gtest.h>

#include <cstring>
#include <functional>

#include "serve/gr00t_protocol.h"
#include "serve/http_error.h"
#include "serve/ndarray.h"

using namespace tether;
using NpType = tether::serve::DType;
using namespace tether::serve;
namespace mp = tether::serve::msgpack;

namespace {

models::ModelSpec spec() {
  models::ModelSpec s;
  s.family = "smolvla";
  s.cameras = {"observation.images.front", "observation.images.wrist"};
  s.camera_prefix = "observation.images.";
  s.state_key = "observation.state";
  s.action_key = "action";
  s.state_dim = 3;
  s.action_dim = 3;
  s.chunk_size = 4;
  return s;
}

void ndarray(mp::Writer& w, NpType t, std::vector<int64_t> shape, const std::string& bytes) {
  gr00t::write_ndarray(w, write_npy(t, shape, bytes));
}

// (B, T, H, W, 3) frames whose every pixel of item b, frame t is 10 * b + t.
std::string video_bytes(int64_t b, int64_t t, int64_t h, int64_t w) {
  std::string out;
  for (int64_t i = 0; i < b; ++i)
    for (int64_t j = 0; j < t; ++j) out += std::string(std::size_t(h * w * 3), char(10 * i + j));
  return out;
}

std::string floats(const std::vector<float>& v) { return std::string(reinterpret_cast<const char*>(v.data()), v.size() * 4); }

struct Obs {
  int64_t batch = 1, frames = 1;
  bool flat = false;
  std::string camera = "front";
  // State groups (name, dim) in the order they are sent. Item b, step t, value k of the concatenation is
  // 100 * b + 10 * t + k.
  std::vector<std::pair<std::string, int64_t>> state = {{"state", 3}};
  NpType video_dtype = NpType::u8;
};

std::string request(const Obs& o, const std::string& token = "", bool with_options = false) {
  mp::Writer w;
  w.map(token.empty() ? 2 : 3);
  w.str("endpoint");
  w.str("get_action");
  if (!token.empty()) {
    w.str("api_token");
    w.str(token);
  }
  w.str("data");
  w.map(with_options ? 2 : 1);
  w.str("observation");
  auto state_groups = [&](const std::string& prefix) {
    int64_t offset = 0;
    for (const auto& [group, dim] : o.state) {
      std::vector<float> values;
      for (int64_t b = 0; b < o.batch; ++b)
        for (int64_t t = 0; t < o.frames; ++t)
          for (int64_t d = 0; d < dim; ++d) values.push_back(float(100 * b + 10 * t + offset + d));
      w.str(prefix + group);
      ndarray(w, NpType::f32, {o.batch, o.frames, dim}, floats(values));
      offset += dim;
    }
  };
  auto language = [&] {
    w.array(uint32_t(o.batch));
    for (int64_t b = 0; b < o.batch; ++b) {
      w.array(1);
      w.str("task " + std::to_string(b));
    }
  };
  if (o.flat) {
    w.map(uint32_t(2 + o.state.size()));
    w.str("video." + o.camera);
    ndarray(w, o.video_dtype, {o.batch, o.frames, 2, 2, 3}, video_bytes(o.batch, o.frames, 2, 2));
    state_groups("state.");
    w.str("task");
    w.array(uint32_t(o.batch));
    for (int64_t b = 0; b < o.batch; ++b) w.str("task " + std::to_string(b));
  } else {
    w.map(3);
    w.str("video");
    w.map(1);
    w.str(o.camera);
    ndarray(w, o.video_dtype, {o.batch, o.frames, 2, 2, 3}, video_bytes(o.batch, o.frames, 2, 2));
    w.str("state");
    w.map(uint32_t(o.state.size()));
    state_groups("");
    w.str("language");
    w.map(1);
    w.str("task");
    language();
  }
  if (with_options) {
    w.str("options");
    w.map(2);
    w.str("seed");
    w.integer(7);
    w.str("episode_id");
    w.array(uint32_t(o.batch));
    for (int64_t b = 0; b < o.batch; ++b) w.str("ep" + std::to_string(b));
  }
  return w.take();
}

std::string code_of(const std::string& message, int64_t index = 0, const models::ModelSpec& model = spec()) {
  try {
    const gr00t::Call call = gr00t::parse_call(message);
    gr00t::decode_item(call, index, model);
  } catch (const HttpError& e) {
    EXPECT_EQ(e.status(), 400);
    return e.code() + ": " + e.what();
  }
  return "ok";
}

}  // namespace

TEST(Gr00tProtocol, NestedBatchWithHistoryTakesEachItemsLastFrame) {
  Obs o;
  o.batch = 2;
  o.frames = 3;
  const std::string msg = request(o, "secret", true);
  const gr00t::Call call = gr00t::parse_call(msg);
  EXPECT_EQ(call.endpoint, gr00t::Endpoint::get_action);
  EXPECT_EQ(call.api_token, "secret");
  const gr00t::Layout layout = gr00t::observation_layout(call);
  EXPECT_FALSE(layout.flat);
  EXPECT_EQ(layout.batch, 2);
  for (int64_t b = 0; b < 2; ++b) {
    const ActRequest r = gr00t::decode_item(call, b, spec());
    const auto& img = r.observation.images.at("observation.images.front");
    EXPECT_EQ(img.height, 2);
    EXPECT_EQ(img.width, 2);
    EXPECT_EQ(uint8_t(img.rgb[0]), uint8_t(10 * b + 2));  // the last of 3 frames
    EXPECT_EQ(r.observation.state, (std::vector<float>{float(100 * b + 20), float(100 * b + 21), float(100 * b + 22)}));
    EXPECT_EQ(r.observation.instruction, "task " + std::to_string(b));
    EXPECT_EQ(r.seed, 7u);
    EXPECT_EQ(r.episode_id, "ep" + std::to_string(b));
  }
}

TEST(Gr00tProtocol, FlatLayoutAndFullCameraKey) {
  Obs o;
  o.flat = true;
  o.camera = "observation.images.wrist";
  const std::string msg = request(o);
  const gr00t::Call call = gr00t::parse_call(msg);
  EXPECT_TRUE(gr00t::observation_layout(call).flat);
  const ActRequest r = gr00t::decode_item(call, 0, spec());
  EXPECT_EQ(r.observation.images.count("observation.images.wrist"), 1u);
  EXPECT_EQ(r.observation.instruction, "task 0");
  EXPECT_FALSE(r.seed.has_value());
}

TEST(Gr00tProtocol, Endpoints) {
  auto call_of = [](const std::string& endpoint) {
    mp::Writer w;
    w.map(1);
    w.str("endpoint");
    w.str(endpoint);
    return w.take();
  };
  for (const auto& [name, ep] : std::vector<std::pair<std::string, gr00t::Endpoint>>{
           {"ping", gr00t::Endpoint::ping}, {"kill", gr00t::Endpoint::kill}, {"reset", gr00t::Endpoint::reset},
           {"get_modality_config", gr00t::Endpoint::get_modality_config}}) {
    const std::string m = call_of(name);
    EXPECT_EQ(gr00t::parse_call(m).endpoint, ep) << name;
  }
  mp::Writer empty;
  empty.map(0);
  const std::string e = empty.take();
  EXPECT_EQ(gr00t::parse_call(e).endpoint, gr00t::Endpoint::get_action);  // upstream's default
  const std::string bad = call_of("explode");
  try {
    gr00t::parse_call(bad);
    FAIL();
  } catch (const HttpError& ex) {
    EXPECT_EQ(ex.code(), "unknown_endpoint");
    EXPECT_NE(std::string(ex.what()).find("Unknown endpoint: explode"), std::string::npos);
  }
}

TEST(Gr00tProtocol, Refusals) {
  EXPECT_EQ(code_of("\xc1").substr(0, 11), "bad_msgpack");
  EXPECT_EQ(code_of("\x93\x01\x02\x03").substr(0, 11), "bad_msgpack");  // an array, not a map
  Obs o;
  o.camera = "top";
  EXPECT_NE(code_of(request(o)).find("unknown_camera: observation.video.top"), std::string::npos);
  o = Obs();
  o.state = {{"joints", 3}};
  EXPECT_NE(code_of(request(o)).find("unknown_field: observation.state.joints"), std::string::npos);
  o = Obs();
  o.state = {{"state", 2}};
  EXPECT_NE(code_of(request(o)).find("invalid_state"), std::string::npos);
  o = Obs();
  o.video_dtype = NpType::f32;
  EXPECT_NE(code_of(request(o)).find("invalid_field: observation.video.front"), std::string::npos);
  // An object (pickled) array is refused by the npy reader, never unpickled.
  mp::Writer w;
  w.map(1);
  w.str("data");
  w.map(1);
  w.str("observation");
  w.map(1);
  w.str("video.front");
  std::string npy = write_npy(NpType::u8, {1}, std::string(1, '\0'));
  const auto at = npy.find("|u1");
  npy.replace(at, 3, "|O ");
  gr00t::write_ndarray(w, npy);
  EXPECT_NE(code_of(w.take()).find("invalid_field: observation.video.front"), std::string::npos);
  // A plain list where an array belongs.
  mp::Writer l;
  l.map(1);
  l.str("data");
  l.map(1);
  l.str("observation");
  l.map(1);
  l.str("state.state");
  l.array(1);
  l.integer(1);
  EXPECT_NE(code_of(l.take()).find("expected a numpy array"), std::string::npos);
  // No observation at all.
  mp::Writer n;
  n.map(1);
  n.str("endpoint");
  n.str("get_action");
  EXPECT_NE(code_of(n.take()).find("missing_field"), std::string::npos);
}

TEST(Gr00tProtocol, Replies) {
  const mp::Value ping = mp::parse(gr00t::ping_reply());
  const std::string ping_bytes = gr00t::ping_reply();
  const mp::Value p = mp::parse(ping_bytes);
  EXPECT_EQ(p.find("status")->bytes, "ok");
  EXPECT_EQ(p.find("message")->bytes, "Server is running");
  const std::string reset = gr00t::reset_reply();
  EXPECT_TRUE(mp::parse(reset).is_map());
  EXPECT_TRUE(mp::parse(reset).entries.empty());
  const std::string kill = gr00t::kill_reply();
  EXPECT_TRUE(mp::parse(kill).is_nil());
  const std::string err = gr00t::error_reply(401, "unauthorized", "no key");
  EXPECT_EQ(mp::parse(err).find("error")->bytes.substr(0, 13), "Unauthorized:");

  const std::string cfg = gr00t::modality_config_reply(spec(), 3);
  const mp::Value c = mp::parse(cfg);
  const mp::Value* video = c.find("video")->find("as_json");
  EXPECT_EQ(video->find("modality_keys")->items.at(0).bytes, "front");
  EXPECT_EQ(video->find("modality_keys")->items.at(1).bytes, "wrist");
  EXPECT_EQ(c.find("action")->find("as_json")->find("delta_indices")->items.size(), 4u);
  EXPECT_EQ(c.find("state")->find("as_json")->find("modality_keys")->items.at(0).bytes, "state");
  EXPECT_TRUE(c.find("language")->find("__ModalityConfig_class__")->boolean);

  std::vector<float> actions(2 * 4 * 3);
  for (std::size_t i = 0; i < actions.size(); ++i) actions[i] = float(i);
  const std::string reply = gr00t::action_reply(models::answered_action_groups(spec(), 3), true, 2, 4, 3, actions,
                                                Json::array({Json::object(), Json::object()}));
  const mp::Value r = mp::parse(reply);
  ASSERT_TRUE(r.is_array());
  ASSERT_EQ(r.items.size(), 2u);
  const NdArray a = parse_npy(r.items[0].find("action.action")->find("as_npy")->bytes);
  EXPECT_EQ(a.dtype, NpType::f32);
  EXPECT_EQ(a.shape, (std::vector<int64_t>{2, 4, 3}));
  EXPECT_EQ(to_float32(a), actions);
  EXPECT_TRUE(r.items[1].find("tether")->is_array());
}

namespace {

// A GR00T-like spec: state = left_arm (2) + gripper (1), action = arm (2) + hand (1).
models::ModelSpec two_group_spec() {
  models::ModelSpec s = spec();
  s.state_groups = {{"left_arm", 2}, {"gripper", 1}};
  s.action_groups = {{"arm", 2}, {"hand", 1}};
  return s;
}

}  // namespace

TEST(Gr00tProtocol, LerobotSpecHasOneStateAndOneActionGroup) {
  models::ModelSpec s = spec();
  s.state_key = "observation.state";
  models::set_single_groups(s);
  ASSERT_EQ(s.state_groups.size(), 1u);
  EXPECT_EQ(s.state_groups[0].name, "state");
  EXPECT_EQ(s.state_groups[0].dim, 3);
  ASSERT_EQ(s.action_groups.size(), 1u);
  EXPECT_EQ(s.action_groups[0].name, "action");
  // A spec built without groups reads as the same single groups.
  EXPECT_EQ(models::state_groups(spec())[0].name, "state");
  EXPECT_EQ(models::action_groups(spec())[0].dim, 3);
  // The one group is also taken under its feature key.
  Obs o;
  o.state = {{"observation.state", 3}};
  EXPECT_EQ(code_of(request(o), 0, s), "ok");
}

TEST(Gr00tProtocol, StateGroupsConcatenateInSpecOrder) {
  const models::ModelSpec s = two_group_spec();
  for (const bool flat : {false, true}) {
    Obs o;
    o.flat = flat;
    o.batch = 2;
    o.frames = 2;
    // Sent in the other order: the spec's order decides the concatenation.
    o.state = {{"gripper", 1}, {"left_arm", 2}};
    const std::string msg = request(o);
    const gr00t::Call call = gr00t::parse_call(msg);
    for (int64_t b = 0; b < 2; ++b) {
      const ActRequest r = gr00t::decode_item(call, b, s);
      // gripper was sent first (offset 0), left_arm after it (offsets 1, 2); the last step is t = 1.
      const float base = float(100 * b + 10);
      EXPECT_EQ(r.observation.state, (std::vector<float>{base + 1, base + 2, base + 0})) << "flat " << flat;
    }
  }
}

TEST(Gr00tProtocol, StateGroupsAreCheckedOneByOne) {
  const models::ModelSpec s = two_group_spec();
  Obs o;
  o.state = {{"left_arm", 2}};
  EXPECT_NE(code_of(request(o), 0, s).find("missing_field: observation.state.gripper is required (1 values"),
            std::string::npos)
      << code_of(request(o), 0, s);
  o.state = {{"left_arm", 2}, {"gripper", 1}, {"tail", 1}};
  const std::string unknown = code_of(request(o), 0, s);
  EXPECT_NE(unknown.find("unknown_field: observation.state.tail: unknown state group"), std::string::npos) << unknown;
  EXPECT_NE(unknown.find("'left_arm' (2 values), 'gripper' (1 values)"), std::string::npos) << unknown;
  o.state = {{"left_arm", 3}, {"gripper", 1}};
  const std::string wrong_size = code_of(request(o), 0, s);
  EXPECT_NE(wrong_size.find("invalid_state: observation.state.left_arm has 3 values, the model expects 2"),
            std::string::npos)
      << wrong_size;
  // The single-group spelling means nothing to a model with several groups.
  o.state = {{"state", 3}};
  EXPECT_NE(code_of(request(o), 0, s).find("unknown_field: observation.state.state"), std::string::npos);
}

TEST(Gr00tProtocol, ActionReplySplitsIntoGroupsAndConfigListsThem) {
  const models::ModelSpec s = two_group_spec();
  std::vector<float> actions(2 * 4 * 3);
  for (std::size_t i = 0; i < actions.size(); ++i) actions[i] = float(i);
  const auto groups = models::answered_action_groups(s, 3);
  for (const bool flat : {false, true}) {
    const std::string reply = gr00t::action_reply(groups, flat, 2, 4, 3, actions, Json::array());
    const mp::Value r = mp::parse(reply);
    ASSERT_TRUE(r.is_array());
    ASSERT_EQ(r.items[0].entries.size(), 2u);
    const NdArray arm = parse_npy(r.items[0].find(flat ? "action.arm" : "arm")->find("as_npy")->bytes);
    const NdArray hand = parse_npy(r.items[0].find(flat ? "action.hand" : "hand")->find("as_npy")->bytes);
    EXPECT_EQ(arm.shape, (std::vector<int64_t>{2, 4, 2}));
    EXPECT_EQ(hand.shape, (std::vector<int64_t>{2, 4, 1}));
    std::vector<float> want_arm, want_hand;
    for (std::size_t row = 0; row < 8; ++row) {
      want_arm.push_back(actions[row * 3]);
      want_arm.push_back(actions[row * 3 + 1]);
      want_hand.push_back(actions[row * 3 + 2]);
    }
    EXPECT_EQ(to_float32(arm), want_arm);
    EXPECT_EQ(to_float32(hand), want_hand);
  }
  // Groups that do not add up to the answer's width: an internal error, never a misaligned split.
  const mp::Value bad = mp::parse(gr00t::action_reply(groups, false, 1, 4, 2, std::vector<float>(8), Json::array()));
  EXPECT_EQ(bad.find("code")->bytes, "internal_error");

  const mp::Value c = mp::parse(gr00t::modality_config_reply(s, 3));
  const mp::Value* state_keys = c.find("state")->find("as_json")->find("modality_keys");
  ASSERT_EQ(state_keys->items.size(), 2u);
  EXPECT_EQ(state_keys->items[0].bytes, "left_arm");
  EXPECT_EQ(state_keys->items[1].bytes, "gripper");
  const mp::Value* action_keys = c.find("action")->find("as_json")->find("modality_keys");
  ASSERT_EQ(action_keys->items.size(), 2u);
  EXPECT_EQ(action_keys->items[0].bytes, "arm");
  const auto groups_of = [&](const char* key) {
    std::vector<std::pair<std::string, int64_t>> out;
    for (const auto& g : c.find("tether")->find(key)->items)
      out.emplace_back(std::string(g.find("name")->bytes), g.find("dim")->integer);
    return out;
  };
  using Groups = std::vector<std::pair<std::string, int64_t>>;
  EXPECT_EQ(groups_of("state_groups"), (Groups{{"left_arm", 2}, {"gripper", 1}}));
  EXPECT_EQ(groups_of("action_groups"), (Groups{{"arm", 2}, {"hand", 1}}));
}

namespace {

// The JSON a msgpack reply of maps, arrays, strings, integers, booleans and nil stands for.
Json msgpack_to_json(const mp::Value& v) {
  switch (v.kind) {
    case mp::Kind::nil: return nullptr;
    case mp::Kind::boolean: return v.boolean;
    case mp::Kind::integer: return v.integer;
    case mp::Kind::str: return std::string(v.bytes);
    case mp::Kind::array: {
      Json out = Json::array();
      for (const auto& item : v.items) out.push_back(msgpack_to_json(item));
      return out;
    }
    case mp::Kind::map: {
      Json out = Json::object();
      for (const auto& [k, item] : v.entries) out[std::string(k.bytes)] = msgpack_to_json(item);
      return out;
    }
    default: ADD_FAILURE() << "unexpected msgpack kind"; return nullptr;
  }
}

}  // namespace

// A GR00T checkpoint's own modality config travels as Isaac-GR00T's server sends it: its encoding fields
// (action_configs, sin/cos and mean/std keys) and its language key. Keys the server answers differently (an
// --embodiment mapping that cuts the output to one group) get null encoding fields, never ones describing other keys.
TEST(Gr00tProtocol, ModalityConfigCarriesTheCheckpointsOwn) {
  models::ModelSpec s = two_group_spec();
  const Json relative = {{"rep", "RELATIVE"}, {"type", "NON_EEF"}, {"format", "DEFAULT"}, {"state_key", "left_arm"}};
  const Json absolute = {{"rep", "ABSOLUTE"}, {"type", "NON_EEF"}, {"format", "DEFAULT"}, {"state_key", nullptr}};
  s.modality_config = {
      {"video", {{"delta_indices", {0}}, {"modality_keys", {"front", "wrist"}}}},
      {"state",
       {{"delta_indices", {0}}, {"modality_keys", {"left_arm", "gripper"}}, {"sin_cos_embedding_keys", {"gripper"}}}},
      {"action",
       {{"delta_indices", {0, 1, 2, 3}}, {"modality_keys", {"arm", "hand"}}, {"mean_std_embedding_keys", {"hand"}},
        {"action_configs", {relative, absolute}}, {"sin_cos_embedding_keys", nullptr}}},
      {"language", {{"delta_indices", {0}}, {"modality_keys", {"annotation.human.task_description"}}}}};
  const auto as_json = [](const std::string& reply, const char* modality) {
    return msgpack_to_json(*mp::parse(reply).find(modality)->find("as_json"));
  };
  const std::string reply = gr00t::modality_config_reply(s, 3);
  for (const char* m : {"video", "state", "action", "language"}) {
    Json want = s.modality_config.at(m);
    for (const char* k : {"sin_cos_embedding_keys", "mean_std_embedding_keys", "action_configs"})
      if (!want.contains(k)) want[k] = nullptr;
    const Json got = as_json(reply, m);
    EXPECT_EQ(got.size(), want.size()) << m;
    for (auto it = want.begin(); it != want.end(); ++it) EXPECT_EQ(got.value(it.key(), Json()), it.value()) << m;
  }
  // An embodiment mapping answers one 5-value group: the checkpoint's action encodings no longer describe it.
  s.action_groups = {{"action", 3}};
  const Json cut = as_json(gr00t::modality_config_reply(s, 5), "action");
  EXPECT_EQ(cut.at("modality_keys"), Json::array({"action"}));
  EXPECT_TRUE(cut.at("action_configs").is_null());
  EXPECT_TRUE(cut.at("mean_std_embedding_keys").is_null());
  // No checkpoint config (a lerobot checkpoint): "task", and nulls.
  EXPECT_EQ(as_json(gr00t::modality_config_reply(spec(), 3), "language").at("modality_keys"), Json::array({"task"}));
}

TEST(Gr00tProtocol, ResetNamesTheEpisodesItEnds) {
  const auto reset = [](const std::function<void(mp::Writer&)>& options) {
    mp::Writer w;
    w.map(2);
    w.str("endpoint");
    w.str("reset");
    w.str("data");
    w.map(1);
    w.str("options");
    options(w);
    return w.take();
  };
  const auto episodes = [](const std::string& message) { return gr00t::reset_episodes(gr00t::parse_call(message)); };
  using Ids = std::vector<std::string>;
  EXPECT_EQ(episodes(reset([](mp::Writer& w) { w.nil(); })), Ids{""});  // the default episode
  EXPECT_EQ(episodes(reset([](mp::Writer& w) { w.map(0); })), Ids{""});
  EXPECT_EQ(episodes(reset([](mp::Writer& w) {
              w.map(1);
              w.str("episode_id");
              w.str("ep7");
            })),
            Ids{"ep7"});
  EXPECT_EQ(episodes(reset([](mp::Writer& w) {
              w.map(1);
              w.str("episode_id");
              w.array(2);
              w.str("a");
              w.str("b");
            })),
            (Ids{"a", "b"}));
  mp::Writer bare;
  bare.map(1);
  bare.str("endpoint");
  bare.str("reset");
  EXPECT_EQ(episodes(bare.take()), Ids{""});  // no data at all
  try {
    episodes(reset([](mp::Writer& w) {
      w.map(1);
      w.str("episode_id");
      w.integer(3);
    }));
    FAIL();
  } catch (const HttpError& e) {
    EXPECT_EQ(e.code(), "invalid_field");
    EXPECT_NE(std::string(e.what()).find("data.options.episode_id"), std::string::npos);
  }
}
