// Base64 codec: RFC 4648 vectors, round trips of every length, and each kind of malformed input.
#include <gtest/gtest.h>

#include "serve/base64.h"

using namespace tether::serve;

namespace {
std::string decode_str(const std::string& s) {
  auto d = base64_decode(s);
  EXPECT_TRUE(d.has_value()) << s;
  return d ? std::string(d->begin(), d->end()) : "";
}
std::string encode_str(const std::string& s) { return base64_encode(reinterpret_cast<const uint8_t*>(s.data()), s.size()); }
}  // namespace

TEST(Base64, Rfc4648Vectors) {
  const std::pair<const char*, const char*> vectors[] = {{"", ""},         {"f", "Zg=="},     {"fo", "Zm8="},
                                                         {"foo", "Zm9v"},  {"foob", "Zm9vYg=="}, {"fooba", "Zm9vYmE="},
                                                         {"foobar", "Zm9vYmFy"}};
  for (const auto& [plain, coded] : vectors) {
    EXPECT_EQ(encode_str(plain), coded);
    EXPECT_EQ(decode_str(coded), plain);
  }
}

TEST(Base64, PaddingIsOptional) {
  EXPECT_EQ(decode_str("Zg"), "f");
  EXPECT_EQ(decode_str("Zm8"), "fo");
}

TEST(Base64, RoundTripsAllByteValuesAndLengths) {
  std::vector<uint8_t> bytes;
  for (int n = 0; n < 300; ++n) {
    const std::string enc = base64_encode(bytes.data(), bytes.size());
    auto dec = base64_decode(enc);
    ASSERT_TRUE(dec.has_value());
    EXPECT_EQ(*dec, bytes) << "length " << n;
    bytes.push_back(uint8_t(n * 37 + 11));
  }
}

TEST(Base64, RejectsMalformedInputWithAReason) {
  for (const char* bad : {"Zm9v!", "Zm 9v", "Zm9v\n", "Z", "Zm9vY", "=Zm9", "Zg=", "Zg===", "Zm=v", "Zh==", "Zm9=",
                          "-_-_"}) {
    std::string why;
    EXPECT_FALSE(base64_decode(bad, &why).has_value()) << bad;
    EXPECT_FALSE(why.empty()) << bad;
  }
  std::string why;
  base64_decode("Zm9v*A==", &why);
  EXPECT_NE(why.find("offset 4"), std::string::npos) << why;
}

// OpenSSL's block decoder trims whitespace at the ends and reads '=' anywhere as zeros; Tether's contract does not.
TEST(Base64, RejectsWhatTheBlockDecoderWouldForgiveAtTheRightOffset) {
  const std::pair<std::string, std::string> cases[] = {
      {" Zm9vYg", "offset 0"},          {"\tZm9vYg=", "offset 0"},     {"Zm9v  ", "offset 4"},
      {"Zm9vZm9v-_", "offset 8"},      {"Zm9vYg\n", "offset 6"},       {"Zm9vYg\r\n", "offset 6"},
      {"Zm9v=Zm9", "offset 4"},        {"Zm9vZg=A", "offset 6"},       {"Zm9v\xC3\xA9Zm", "offset 4"},
      {"Zm9vZm9vZm9vZm9vZ m9vZg", "offset 17"}};
  for (const auto& [bad, where] : cases) {
    std::string why;
    EXPECT_FALSE(base64_decode(bad, &why).has_value()) << bad;
    EXPECT_NE(why.find("invalid base64 character at " + where), std::string::npos) << bad << ": " << why;
  }
}

TEST(Base64, PaddingAndTrailingBitsAreCheckedBesideTheLibrary) {
  std::string why;
  EXPECT_FALSE(base64_decode("Zm9vZ=", &why).has_value());
  EXPECT_NE(why.find("padding does not complete"), std::string::npos) << why;
  EXPECT_FALSE(base64_decode("Zm9vYh", &why).has_value());  // 'h' leaves non-zero unused bits
  EXPECT_NE(why.find("non-zero padding bits"), std::string::npos) << why;
  EXPECT_FALSE(base64_decode("Zm9vYmF=", &why).has_value());  // 'F' leaves non-zero unused bits
  EXPECT_NE(why.find("non-zero padding bits"), std::string::npos) << why;
  // The decoded length counts only the real bytes, padded or not.
  EXPECT_EQ(base64_decode("Zm9vYmE=")->size(), 5u);
  EXPECT_EQ(base64_decode("Zm9vYmE")->size(), 5u);
  EXPECT_EQ(base64_decode("Zm9vYg==")->size(), 4u);
  EXPECT_EQ(base64_decode("")->size(), 0u);
}

TEST(Base64, LargePayloadRoundTrips) {
  std::vector<uint8_t> bytes(512 * 512 * 3 + 1);
  for (std::size_t i = 0; i < bytes.size(); ++i) bytes[i] = uint8_t(i * 131 + (i >> 9));
  const auto dec = base64_decode(base64_encode(bytes.data(), bytes.size()));
  ASSERT_TRUE(dec.has_value());
  EXPECT_EQ(*dec, bytes);
}
