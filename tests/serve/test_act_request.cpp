// POST /act body parsing: the accepted forms, and each error code of the API contract with its field named.
#include <gtest/gtest.h>

#include <fstream>

#include "serve/act_request.h"
#include "serve/base64.h"

using namespace tether;
using namespace tether::serve;

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

std::string file_base64(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  const std::string bytes((std::istreambuf_iterator<char>(in)), {});
  EXPECT_FALSE(bytes.empty()) << path;
  return base64_encode(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
}

const std::string& png_b64() {
  static const std::string s = file_base64(std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png");
  return s;
}

Json raw_image(int h, int w, uint8_t fill = 7) {
  std::vector<uint8_t> px(std::size_t(h) * w * 3, fill);
  return {{"data", base64_encode(px.data(), px.size())}, {"shape", {h, w, 3}}};
}

Json good() { return {{"instruction", "pick"}, {"state", {1.0, 2.0, 3.0}}, {"images", {{"front", png_b64()}}}}; }

// Expects a 400 with `code`, and the message to mention `mention`.
void expect_error(const std::string& body, const std::string& code, const std::string& mention = "") {
  try {
    parse_act_request(body, spec());
    ADD_FAILURE() << "accepted: " << body.substr(0, 200);
  } catch (const HttpError& e) {
    EXPECT_EQ(e.status(), 400) << body.substr(0, 200);
    EXPECT_EQ(e.code(), code) << e.what();
    EXPECT_NE(std::string(e.what()).find(mention), std::string::npos) << e.what();
  }
}
void expect_error(const Json& body, const std::string& code, const std::string& mention = "") {
  expect_error(body.dump(), code, mention);
}

}  // namespace

TEST(ActRequest, AcceptsPngUnderShortCameraName) {
  const ActRequest r = parse_act_request(good().dump(), spec());
  ASSERT_EQ(r.observation.images.size(), 1u);
  const auto& img = r.observation.images.at("observation.images.front");
  EXPECT_GT(img.width, 0);
  EXPECT_EQ(img.rgb.size(), std::size_t(img.width) * img.height * 3);
  EXPECT_EQ(r.observation.state, std::vector<float>({1, 2, 3}));
  EXPECT_EQ(r.observation.instruction, "pick");
  EXPECT_FALSE(r.seed.has_value());
  EXPECT_FALSE(r.episode_id.has_value());
}

TEST(ActRequest, AcceptsFullCameraKeyRawImageSeedAndEpisode) {
  Json j = good();
  j["images"] = {{"observation.images.wrist", raw_image(2, 5, 9)}, {"front", raw_image(3, 4)}};
  j["seed"] = 18446744073709551615ull;
  j["episode_id"] = "ep-1";
  const ActRequest r = parse_act_request(j.dump(), spec());
  const auto& wrist = r.observation.images.at("observation.images.wrist");
  EXPECT_EQ(wrist.height, 2);
  EXPECT_EQ(wrist.width, 5);
  EXPECT_EQ(wrist.rgb, std::vector<uint8_t>(30, 9));
  EXPECT_EQ(r.observation.images.at("observation.images.front").height, 3);
  EXPECT_EQ(*r.seed, 18446744073709551615ull);
  EXPECT_EQ(*r.episode_id, "ep-1");
}

TEST(ActRequest, SingleImageMeansTheFirstCamera) {
  Json j = good();
  j.erase("images");
  j["image"] = raw_image(2, 2);
  const ActRequest r = parse_act_request(j.dump(), spec());
  EXPECT_EQ(r.observation.images.count("observation.images.front"), 1u);
}

TEST(ActRequest, NullOptionalFieldsAreAbsent) {
  Json j = good();
  j["seed"] = nullptr;
  j["episode_id"] = nullptr;
  const ActRequest r = parse_act_request(j.dump(), spec());
  EXPECT_FALSE(r.seed.has_value());
  EXPECT_FALSE(r.episode_id.has_value());
}

TEST(ActRequest, BadJson) {
  expect_error(std::string("{\"instruction\": "), "bad_json");
  expect_error(std::string(""), "bad_json");
  expect_error(std::string("[1, 2]"), "bad_json", "object");
  expect_error(std::string(200, '[') + std::string(200, ']'), "bad_json", "nested");
  expect_error(std::string("{\"state\": NaN}"), "bad_json");
}

TEST(ActRequest, MissingFields) {
  Json j = good();
  j.erase("instruction");
  expect_error(j, "missing_field", "instruction");
  j = good();
  j.erase("state");
  expect_error(j, "missing_field", "state");
  j = good();
  j.erase("images");
  expect_error(j, "missing_field", "image");
  j = good();
  j["images"] = Json::object();
  expect_error(j, "missing_field", "images");
}

TEST(ActRequest, UnknownField) {
  Json j = good();
  j["noise"] = {1, 2};
  expect_error(j, "unknown_field", "'noise'");
}

TEST(ActRequest, InvalidFieldTypes) {
  Json j = good();
  j["instruction"] = 3;
  expect_error(j, "invalid_field", "instruction");
  j = good();
  j["state"] = "1,2,3";
  expect_error(j, "invalid_field", "state");
  j = good();
  j["state"] = {1, "2", 3};
  expect_error(j, "invalid_field", "state[1]");
  j = good();
  j["state"] = {1, true, 3};
  expect_error(j, "invalid_field", "state[1]");
  j = good();
  j["images"] = {png_b64()};
  expect_error(j, "invalid_field", "images");
  j = good();
  j["images"]["front"] = 12;
  expect_error(j, "invalid_field", "images.front");
  j = good();
  j["episode_id"] = 5;
  expect_error(j, "invalid_field", "episode_id");
  for (const Json& seed : {Json(-1), Json(1.5), Json("3"), Json(true)}) {
    j = good();
    j["seed"] = seed;
    expect_error(j, "invalid_field", "seed");
  }
  j = good();
  j["image"] = png_b64();
  expect_error(j, "invalid_field", "not both");
  j = good();
  j["images"] = {{"front", png_b64()}, {"observation.images.front", png_b64()}};
  expect_error(j, "invalid_field", "twice");
}

TEST(ActRequest, InvalidBase64AndRawShapes) {
  Json j = good();
  j["images"]["front"] = "not*base64";
  expect_error(j, "invalid_field", "images.front");
  j["images"]["front"] = "";
  expect_error(j, "invalid_field", "empty");
  const std::vector<std::pair<Json, std::string>> raws = {
      {{{"data", "AAAA"}, {"shape", {1, 1, 3}}}, "images.front"},           // 3 bytes: fine, used below as sanity
      {{{"data", "AAAA"}, {"shape", {1, 1, 4}}}, "last dimension"},         // not RGB
      {{{"data", "AAAA"}, {"shape", {2, 1, 3}}}, "needs 6"},                // wrong byte count
      {{{"data", "AAAA"}, {"shape", {1, 3}}}, "[H, W, 3]"},                 // wrong rank
      {{{"data", "AAAA"}, {"shape", {0, 1, 3}}}, "shape[0]"},               // empty
      {{{"data", "AAAA"}, {"shape", {-1, 1, 3}}}, "shape[0]"},              // negative
      {{{"data", "AAAA"}, {"shape", {1.5, 1, 3}}}, "shape[0]"},             // not an integer
      {{{"data", "AAAA"}, {"shape", {100000, 100000, 3}}}, "pixel limit"},  // bomb
      {{{"data", "A*AA"}, {"shape", {1, 1, 3}}}, "offset 1"},               // bad base64
      {{{"data", 5}, {"shape", {1, 1, 3}}}, ".data"},                        // wrong type
      {{{"shape", {1, 1, 3}}}, "both"},                                      // missing data
      {{{"data", "AAAA"}, {"shape", {1, 1, 3}}, {"dtype", "uint8"}}, "dtype"},
  };
  for (std::size_t i = 0; i < raws.size(); ++i) {
    j = good();
    j["images"]["front"] = raws[i].first;
    if (i == 0) {
      EXPECT_NO_THROW(parse_act_request(j.dump(), spec()));
      continue;
    }
    expect_error(j, "invalid_field", raws[i].second);
  }
}

TEST(ActRequest, InvalidState) {
  Json j = good();
  j["state"] = {1, 2};
  expect_error(j, "invalid_state", "expects 3");
  j["state"] = {1, 2, 3, 4};
  expect_error(j, "invalid_state", "expects 3");
  j["state"] = {1, 2, 1e39};  // finite as a double, infinite as float32
  expect_error(j, "invalid_state", "state[2]");
  // Beyond double range: valid JSON syntax, an invalid value.
  expect_error(std::string(R"({"instruction": "x", "state": [1, 1e999, 2], "image": "AA"})"), "invalid_state", "state[1]");
  expect_error(std::string(R"({"instruction": "x", "state": [1, 2, -1E+999], "image": "AA"})"), "invalid_state", "state[2]");
  expect_error(std::string(R"({"instruction": "1e999", "state": [1, 2, 3], "image": {"data": "AAAA", "shape": [1, 1, 3]},
                              "seed": 1e999})"),
               "invalid_field", "seed");
}

TEST(ActRequest, InvalidImage) {
  const std::string bad = std::string(TETHER_FIXTURES_DIR) + "/vision/bad/";
  for (const char* f : {"random.bin", "bad_crc.png", "header_only.jpg", "not_an_image.gif", "bomb_400mp.png"}) {
    Json j = good();
    j["images"]["front"] = file_base64(bad + f);
    expect_error(j, "invalid_image", "images.front");
  }
}

TEST(ActRequest, UnknownCamera) {
  Json j = good();
  j["images"] = {{"top", png_b64()}};
  expect_error(j, "unknown_camera", "observation.images.wrist");
  j["images"] = {{"observation.images.top", png_b64()}};
  expect_error(j, "unknown_camera", "top");
}

TEST(ActRequest, ResolvesCameraNames) {
  const auto cams = spec();
  EXPECT_EQ(resolve_camera("front", cams), "observation.images.front");
  EXPECT_EQ(resolve_camera("observation.images.wrist", cams), "observation.images.wrist");
  EXPECT_FALSE(resolve_camera("images.front", cams).has_value());
  EXPECT_FALSE(resolve_camera("", cams).has_value());
}

// Bodies simdjson refuses or reads differently from nlohmann are decided by nlohmann's reading, as before simdjson.
TEST(ActRequest, SimdjsonAndNlohmannAgreeOnTheEdges) {
  const std::string img = R"("image": {"data": "AAAA", "shape": [1, 1, 3]})";
  // A repeated key: the last value counts (nlohmann's reading), not the first.
  const ActRequest r = parse_act_request(
      R"({"instruction": "first", "state": [1, 2, 3], "instruction": "last", "seed": 4, )" + img + "}", spec());
  EXPECT_EQ(r.observation.instruction, "last");
  EXPECT_EQ(r.seed, 4u);
  // A UTF-8 byte order mark is skipped by nlohmann; a number beyond uint64 is a float there (not a valid seed).
  EXPECT_EQ(parse_act_request("\xEF\xBB\xBF{\"instruction\": \"x\", \"state\": [1, 2, 3], " + img + "}", spec())
                .observation.instruction, "x");
  expect_error(R"({"instruction": "x", "state": [1, 2, 3], "seed": 18446744073709551616, )" + img + "}", "invalid_field",
               "seed");
  // Nesting: within nlohmann's limit a wrong type, past it bad_json.
  auto nested = [](int levels) { return std::string(std::size_t(levels), '[') + std::string(std::size_t(levels), ']'); };
  expect_error(R"({"instruction": "x", "state": )" + nested(kMaxJsonDepth - 2) + "}", "invalid_field", "state[0]");
  expect_error(R"({"instruction": "x", "state": )" + nested(kMaxJsonDepth + 4) + "}", "bad_json", "nested deeper");
  // Lone surrogates and invalid UTF-8 in a string are not JSON text.
  expect_error(R"({"instruction": "\udc00", "state": [1, 2, 3], )" + img + "}", "bad_json");
  expect_error(R"({"instruction": "\ud800", "state": [1, 2, 3], )" + img + "}", "bad_json");
  expect_error("{\"instruction\": \"\xC3\x28\", \"state\": [1, 2, 3], " + img + "}", "bad_json");
  // Trailing bytes after the object, and a mistake after a wrong field: the syntax error is reported.
  expect_error(R"({"instruction": "x", "state": [1, 2, 3], )" + img + "} x", "bad_json");
  expect_error(std::string(R"({"state": "wrong", "instruction": "x", )"), "bad_json");
  // Of two faults the first in key order is named, whatever the body's order.
  expect_error(R"({"zzz": 1, "instruction": "x", "aaa": 2, "state": [1, 2, 3], )" + img + "}", "unknown_field", "'aaa'");
  // JSON escapes in a base64 string are undone before decoding ("\/" is "/").
  const ActRequest escaped = parse_act_request(
      R"({"instruction": "x", "state": [1, 2, 3], "image": {"data": "\/\/\/\/", "shape": [1, 1, 3]}})", spec());
  EXPECT_EQ(escaped.observation.images.begin()->second.rgb, (std::vector<uint8_t>{0xFF, 0xFF, 0xFF}));
}
