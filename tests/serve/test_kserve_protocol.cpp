// The Open Inference Protocol v2 decoder and encoder as pure functions: JSON and binary tensor data, BYTES framing,
// batches, every refusal naming its tensor, the outputs requested, and the metadata.
#include <gtest/gtest.h>

#include <cstring>

#include "serve/kserve_protocol.h"

using namespace tether;
using namespace tether::serve;
using namespace tether::serve::kserve;

namespace {

models::ModelSpec spec() {
  models::ModelSpec s;
  s.family = "fake";
  s.cameras = {"observation.images.front", "observation.images.wrist"};
  s.camera_prefix = "observation.images.";
  s.state_dim = 3;
  s.action_dim = 2;
  s.chunk_size = 4;
  return s;
}

Json tensor(const std::string& name, const std::string& datatype, std::vector<int64_t> shape, Json data) {
  return {{"name", name}, {"datatype", datatype}, {"shape", std::move(shape)}, {"data", std::move(data)}};
}

// One item in JSON: a 1x2 image, state [1, 2, 3].
Json one_item() {
  return {{"inputs",
           {tensor("instruction", "BYTES", {1}, {"pick"}), tensor("state", "FP32", {1, 3}, {1.0, 2.0, 3.0}),
            tensor("image.front", "UINT8", {1, 1, 2, 3}, {1, 2, 3, 4, 5, 6})}}};
}

InferRequest decode(const Json& j) { return decode_infer_request(j.dump(), "", spec()); }

// Decoding `j` fails with 400 `code` and a message containing `needle`.
void expect_refused(const Json& j, const std::string& code, const std::string& needle, const std::string& tail = "",
                    bool binary = false) {
  std::string body = j.dump();
  const std::string header_length = binary ? std::to_string(body.size()) : "";
  body += tail;
  try {
    decode_infer_request(body, header_length, spec());
    FAIL() << "accepted: " << j.dump();
  } catch (const HttpError& e) {
    EXPECT_EQ(e.status(), 400);
    EXPECT_EQ(e.code(), code) << e.what();
    EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
  }
}

template <typename T>
std::string raw(const std::vector<T>& v) {
  return std::string(reinterpret_cast<const char*>(v.data()), v.size() * sizeof(T));
}

std::string bytes_element(const std::string& s) {
  const auto len = uint32_t(s.size());
  return std::string(reinterpret_cast<const char*>(&len), 4) + s;
}

Json binary_tensor(const std::string& name, const std::string& datatype, std::vector<int64_t> shape, std::size_t size) {
  return {{"name", name}, {"datatype", datatype}, {"shape", std::move(shape)}, {"parameters", {{"binary_data_size", size}}}};
}

}  // namespace

TEST(ServerKServeProtocol, DecodesJsonTensors) {
  Json j = one_item();
  j["id"] = "req-7";
  j["inputs"].push_back(tensor("seed", "INT64", {1}, {42}));
  j["inputs"].push_back(tensor("episode_id", "BYTES", {1, 1}, {"ep"}));
  const InferRequest r = decode(j);
  ASSERT_EQ(r.items.size(), 1u);
  EXPECT_EQ(r.id, "req-7");
  const auto& obs = r.items[0].observation;
  EXPECT_EQ(obs.instruction, "pick");
  EXPECT_EQ(obs.state, (std::vector<float>{1, 2, 3}));
  ASSERT_EQ(obs.images.count("observation.images.front"), 1u);
  const auto& img = obs.images.at("observation.images.front");
  EXPECT_EQ(img.height, 1);
  EXPECT_EQ(img.width, 2);
  EXPECT_EQ(img.rgb, (std::vector<uint8_t>{1, 2, 3, 4, 5, 6}));
  EXPECT_EQ(r.items[0].seed, 42u);
  EXPECT_EQ(r.items[0].episode_id, "ep");
  // No outputs requested: every output, as JSON.
  ASSERT_EQ(r.outputs.size(), 2u);
  EXPECT_EQ(r.outputs[0].name, "actions");
  EXPECT_FALSE(r.outputs[0].binary);
}

TEST(ServerKServeProtocol, NestedDataAndFullCameraKeys) {
  Json j = one_item();
  j["inputs"][1]["data"] = {{1.0, 2.0, 3.0}};
  j["inputs"][2] = tensor("image.observation.images.wrist", "UINT8", {1, 1, 2, 3}, {{{{1, 2, 3}, {4, 5, 6}}}});
  const InferRequest r = decode(j);
  EXPECT_EQ(r.items[0].observation.state, (std::vector<float>{1, 2, 3}));
  EXPECT_EQ(r.items[0].observation.images.count("observation.images.wrist"), 1u);
}

TEST(ServerKServeProtocol, DecodesBinaryTensorsAndSplitsTheBatch) {
  const std::string instr = bytes_element("pick") + bytes_element("place");
  const std::vector<float> state = {1, 2, 3, 4, 5, 6};
  const std::vector<uint8_t> pixels = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12};  // 2 items of 1x2
  const std::vector<uint64_t> seeds = {5, 6};
  const Json j = {{"inputs",
                   {binary_tensor("instruction", "BYTES", {2}, instr.size()),
                    binary_tensor("state", "FP32", {2, 3}, state.size() * 4),
                    binary_tensor("image.wrist", "UINT8", {2, 1, 2, 3}, pixels.size()),
                    binary_tensor("seed", "UINT64", {2}, 16)}},
                  {"parameters", {{"binary_data_output", true}}},
                  {"outputs", {{{"name", "actions"}}, {{"name", "action_source"}, {"parameters", {{"binary_data", false}}}}}}};
  const std::string header = j.dump();
  const std::string body = header + instr + raw(state) + raw(pixels) + raw(seeds);
  const InferRequest r = decode_infer_request(body, std::to_string(header.size()), spec());
  ASSERT_EQ(r.items.size(), 2u);
  EXPECT_EQ(r.items[0].observation.instruction, "pick");
  EXPECT_EQ(r.items[1].observation.instruction, "place");
  EXPECT_EQ(r.items[1].observation.state, (std::vector<float>{4, 5, 6}));
  EXPECT_EQ(r.items[1].observation.images.at("observation.images.wrist").rgb,
            (std::vector<uint8_t>{7, 8, 9, 10, 11, 12}));
  EXPECT_EQ(r.items[0].seed, 5u);
  EXPECT_EQ(r.items[1].seed, 6u);
  // binary_data_output is the default; an output's own binary_data overrides it.
  ASSERT_EQ(r.outputs.size(), 2u);
  EXPECT_TRUE(r.outputs[0].binary);
  EXPECT_FALSE(r.outputs[1].binary);
}

TEST(ServerKServeProtocol, RefusesWhatTheModelDoesNotTake) {
  Json j = one_item();
  j["inputs"].push_back(tensor("temperature", "FP32", {1}, {1.0}));
  expect_refused(j, "unknown_field", "'temperature'");
  j = one_item();
  j["inputs"][2]["name"] = "image.top";
  expect_refused(j, "unknown_camera", "image.top");
  j = one_item();
  j["inputs"][1]["datatype"] = "FP64";
  expect_refused(j, "invalid_field", "input 'state': datatype 'FP64'");
  j = one_item();
  j["inputs"][0]["datatype"] = "STRING";
  expect_refused(j, "invalid_field", "not a v2 datatype");
  j = one_item();
  j["inputs"][1]["shape"] = {1, 4};
  j["inputs"][1]["data"] = {1, 2, 3, 4};
  expect_refused(j, "invalid_state", "input 'state': shape [1, 4]");
  j = one_item();
  j["inputs"][2]["shape"] = {1, 1, 2, 4};
  expect_refused(j, "invalid_field", "input 'image.front': shape [1, 1, 2, 4]");
  j = one_item();
  j["inputs"][2]["data"] = {1, 2, 3, 4, 5};
  expect_refused(j, "invalid_field", "'data' has 5 elements");
  j = one_item();
  j["inputs"][2]["data"] = {1, 2, 3, 4, 5, 256};
  expect_refused(j, "invalid_field", "data[5] is 256");
  j = one_item();
  j["inputs"][0]["data"] = {7};
  expect_refused(j, "invalid_field", "expected a string");
  j = one_item();
  j["inputs"].push_back(tensor("seed", "INT64", {1}, {-1}));
  expect_refused(j, "invalid_field", "input 'seed'");
  j = one_item();
  j["inputs"].push_back(j["inputs"][2]);
  expect_refused(j, "invalid_field", "given twice");
  j = one_item();
  j["inputs"][1]["shape"] = {2, 3};
  j["inputs"][1]["data"] = {1, 2, 3, 4, 5, 6};
  expect_refused(j, "invalid_field", "input 'state': batch size 2, but input 'instruction' has 1");
  j = one_item();
  j["inputs"].erase(1);
  expect_refused(j, "missing_field", "'state'");
  j = one_item();
  j["inputs"].erase(2);
  expect_refused(j, "missing_field", "image");
  j = one_item();
  j["inputs"][1]["data"] = {1.0, 2.0, 1e39};  // beyond float32: not finite
  expect_refused(j, "invalid_state", "state[2]");
  expect_refused(Json::array(), "bad_json", "JSON object");
  expect_refused(Json{{"inputs", Json::array()}}, "missing_field", "'inputs'");
  j = one_item();
  j["outputs"] = {{{"name", "logits"}}};
  expect_refused(j, "unknown_field", "output tensor 'logits'");
  j = one_item();
  j["inputs"][1]["parameters"] = {{"shared_memory_region", "r"}};
  expect_refused(j, "invalid_field", "shared memory");
}

TEST(ServerKServeProtocol, RefusesBrokenJsonAndHeaderLengths) {
  try {
    decode_infer_request("{\"inputs\": [", "", spec());
    FAIL();
  } catch (const HttpError& e) {
    EXPECT_EQ(e.code(), "bad_json");
  }
  const std::string body = one_item().dump();
  for (const std::string& bad : std::vector<std::string>{"12x", "-1", std::to_string(body.size() + 1)}) {
    try {
      decode_infer_request(body, bad, spec());
      FAIL() << bad;
    } catch (const HttpError& e) {
      EXPECT_EQ(e.code(), "invalid_field");
      EXPECT_NE(std::string(e.what()).find("Inference-Header-Content-Length"), std::string::npos) << e.what();
    }
  }
  // Binary sizes without the header that says where the JSON ends.
  Json j = one_item();
  j["inputs"][1] = binary_tensor("state", "FP32", {1, 3}, 12);
  expect_refused(j, "invalid_field", "no Inference-Header-Content-Length");
}

TEST(ServerKServeProtocol, RefusesTruncatedAndLeftoverBinaryData) {
  Json j = one_item();
  j["inputs"][1] = binary_tensor("state", "FP32", {1, 3}, 12);
  const std::vector<float> state = {1, 2, 3};
  expect_refused(j, "invalid_field", "input 'state': binary_data_size 12, but only 8 bytes", raw(state).substr(0, 8),
                 true);
  expect_refused(j, "invalid_field", "2 bytes of binary data follow", raw(state) + "xx", true);
  j["inputs"][1] = binary_tensor("state", "FP32", {1, 3}, 8);
  expect_refused(j, "invalid_field", "binary_data_size 8, shape [1, 3] of FP32 needs 12", raw(state).substr(0, 8), true);
  // BYTES: a length that runs past the tensor's data.
  j = one_item();
  const std::string instr = bytes_element("pick").substr(0, 6);
  j["inputs"][0] = binary_tensor("instruction", "BYTES", {1}, instr.size());
  expect_refused(j, "invalid_field", "element 0 declares 4 bytes", instr, true);
  j["inputs"][0] = binary_tensor("instruction", "BYTES", {1}, 2);
  expect_refused(j, "invalid_field", "4-byte length", "ab", true);
  // An instruction that is not UTF-8.
  const std::string bad = bytes_element("\xff\xfe");
  j["inputs"][0] = binary_tensor("instruction", "BYTES", {1}, bad.size());
  expect_refused(j, "invalid_field", "UTF-8", bad, true);
}

TEST(ServerKServeProtocol, NamesTheItemThatFailsItsCheck) {
  const Json j = {{"inputs",
                   {tensor("instruction", "BYTES", {2}, Json::array({"a", "b"})),
                    tensor("state", "FP32", {2, 3}, {1.0, 2.0, 3.0, 4.0, 5.0, 1e39}),
                    tensor("image.front", "UINT8", {2, 1, 1, 3}, {1, 2, 3, 4, 5, 6})}}};
  expect_refused(j, "invalid_state", "item 1: state[2]");
}

TEST(ServerKServeProtocol, RefusesHugeShapesBeforeAllocating) {
  Json j = one_item();
  j["inputs"][2]["shape"] = {1, 1 << 20, 1 << 20, 3};
  expect_refused(j, "invalid_field", "pixel limit");
  j = one_item();
  j["inputs"][0]["shape"] = {uint64_t(1) << 50};
  expect_refused(j, "invalid_field", "dimensions must be integers");
  j = one_item();
  j["inputs"][0]["shape"] = {5000};
  expect_refused(j, "invalid_field", "at most 1024");
}

TEST(ServerKServeProtocol, EncodesJsonAndBinaryOutputs) {
  InferRequest req;
  req.id = "x1";
  req.outputs = {{"actions", false}, {"action_source", false}};
  std::vector<ItemAnswer> items(2);
  items[0] = {{1, 2, 3, 4}, 2, 2, "model"};
  items[1] = {{5, 6, 7, 8}, 2, 2, "last_good"};
  EncodedResponse enc = encode_infer_response("demo", req, items);
  EXPECT_FALSE(enc.header_length);
  const Json j = Json::parse(enc.body);
  EXPECT_EQ(j["model_name"], "demo");
  EXPECT_EQ(j["id"], "x1");
  EXPECT_EQ(j["outputs"][0]["shape"], Json({2, 2, 2}));
  EXPECT_EQ(j["outputs"][0]["data"], Json({1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0}));
  EXPECT_EQ(j["outputs"][1]["data"], Json::array({"model", "last_good"}));

  req.outputs = {{"actions", true}, {"action_source", true}};
  enc = encode_infer_response("demo", req, items);
  ASSERT_TRUE(enc.header_length);
  const Json h = Json::parse(enc.body.substr(0, *enc.header_length));
  EXPECT_EQ(h["outputs"][0]["parameters"]["binary_data_size"], 32);
  EXPECT_FALSE(h["outputs"][0].contains("data"));
  const std::string tail = enc.body.substr(*enc.header_length);
  ASSERT_EQ(tail.size(), 32u + 4 + 5 + 4 + 9);
  float f[8];
  std::memcpy(f, tail.data(), 32);
  EXPECT_EQ(f[7], 8.0f);
  EXPECT_EQ(tail.substr(32), bytes_element("model") + bytes_element("last_good"));

  items[1].rows = 1;
  items[1].actions = {5, 6};
  EXPECT_THROW(encode_infer_response("demo", req, items), HttpError);
}

TEST(ServerKServeProtocol, MetadataNamesEveryTensor) {
  const Json m = model_metadata("demo", spec(), 2);
  EXPECT_EQ(m["name"], "demo");
  EXPECT_EQ(m["versions"], Json({"1"}));
  EXPECT_EQ(m["platform"], "tether_fake");
  std::vector<std::string> names;
  for (const auto& t : m["inputs"]) names.push_back(t["name"]);
  EXPECT_EQ(names, (std::vector<std::string>{"instruction", "state", "image.front", "image.wrist", "seed", "episode_id"}));
  EXPECT_EQ(m["inputs"][1]["shape"], Json({-1, 3}));
  EXPECT_EQ(m["inputs"][2]["shape"], Json({-1, -1, -1, 3}));
  EXPECT_EQ(m["outputs"][0]["shape"], Json({-1, 4, 2}));
  const Json s = server_metadata("1.2.3");
  EXPECT_EQ(s["extensions"], Json({"binary_tensor_data"}));
  EXPECT_EQ(error_json("boom"), Json({{"error", "boom"}}));
}
