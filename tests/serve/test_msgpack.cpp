// The bounded msgpack reader and the writer of the binary transports.
#include "serve/msgpack.h"

#include <gtest/gtest.h>

namespace tether::serve::msgpack {
namespace {

TEST(Msgpack, WritesAndReadsEveryKind) {
  Writer w;
  w.map(9);
  w.str("nil"), w.nil();
  w.str("bool"), w.boolean(true);
  w.str("neg"), w.integer(-70000);
  w.str("big"), w.uinteger(18446744073709551615ull);
  w.str("f32"), w.float32(1.5f);
  w.str("f64"), w.float64(-2.25);
  w.bin(std::string_view("bin_key")), w.bin(std::string_view("\x00\x01\x02", 3));
  w.str("list"), w.array(2), w.integer(1), w.str("two");
  w.str("long"), w.str(std::string(70000, 'x'));
  const std::string buf = w.take();
  const Value v = parse(buf);
  ASSERT_TRUE(v.is_map());
  ASSERT_EQ(v.entries.size(), 9u);
  EXPECT_TRUE(v.find("nil")->is_nil());
  EXPECT_TRUE(v.find("bool")->boolean);
  EXPECT_EQ(v.find("neg")->integer, -70000);
  EXPECT_TRUE(v.find("big")->above_int64);
  EXPECT_EQ(v.find("big")->uinteger, 18446744073709551615ull);
  EXPECT_EQ(v.find("f32")->kind, Kind::float32);
  EXPECT_EQ(v.find("f32")->as_double(), 1.5);
  EXPECT_EQ(v.find("f64")->as_double(), -2.25);
  // A binary key is found by its bytes, as openpi's msgpack-numpy writes them.
  ASSERT_NE(v.find("bin_key"), nullptr);
  EXPECT_TRUE(v.find("bin_key")->is_bin());
  EXPECT_EQ(v.find("bin_key")->bytes, std::string_view("\x00\x01\x02", 3));
  EXPECT_EQ(v.find("list")->items.at(1).bytes, "two");
  EXPECT_EQ(v.find("long")->bytes.size(), 70000u);
  EXPECT_EQ(v.find("absent"), nullptr);
}

TEST(Msgpack, RefusesTruncatedInputAtEveryLength) {
  Writer w;
  w.map(2);
  w.str("data"), w.bin(std::string(300, 'a'));
  w.str("shape"), w.array(3), w.integer(10), w.integer(10), w.integer(3);
  const std::string buf = w.take();
  for (std::size_t n = 0; n < buf.size(); ++n) EXPECT_THROW(parse(std::string_view(buf.data(), n)), Error) << n;
  EXPECT_NO_THROW(parse(buf));
  EXPECT_THROW(parse(buf + "x"), Error);  // trailing bytes
}

TEST(Msgpack, RefusesCountsBeyondTheBytesLeft) {
  // array32 announcing 2^32-1 items (msgpuck's own check wraps its counter on this), map32 likewise, str32 of 4 GiB.
  for (const std::string& hostile :
       {std::string("\xdd\xff\xff\xff\xff\x01", 6), std::string("\xdf\xff\xff\xff\xff\x01\x01", 7),
        std::string("\xdb\xff\xff\xff\xff" "abc", 8), std::string("\xc6\x7f\xff\xff\xff" "abc", 8)}) {
    try {
      parse(hostile);
      ADD_FAILURE() << "accepted";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("malformed msgpack"), std::string::npos) << e.what();
    }
  }
}

TEST(Msgpack, LimitsDepthAndElements) {
  std::string deep(100, '\x91');  // 100 nested one-item arrays
  deep += '\xc0';
  EXPECT_THROW(parse(deep), Error);
  Limits small;
  small.max_elements = 10;
  Writer w;
  w.array(11);
  for (int i = 0; i < 11; ++i) w.nil();
  EXPECT_THROW(parse(w.buffer(), small), Error);
  EXPECT_NO_THROW(parse(w.buffer()));
}

TEST(Msgpack, RefusesExtensionTypes) {
  EXPECT_THROW(parse(std::string("\xd4\x01\x00", 3)), Error);  // fixext1
  EXPECT_THROW(parse(""), Error);
}

}  // namespace
}  // namespace tether::serve::msgpack
