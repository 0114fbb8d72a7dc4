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
