// Content digests: FIPS 180 sha256 vectors, git blob ids, file hashing and its errors.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "core/error.h"
#include "core/hash.h"
#include "scratch_dir.h"

using namespace tether;

TEST(Sha256, FipsVectors) {
  EXPECT_EQ(sha256_hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  EXPECT_EQ(sha256_hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  EXPECT_EQ(sha256_hex("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
            "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
  EXPECT_EQ(sha256_hex(std::string(1000000, 'a')), "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0");
}

TEST(Sha256, HashesFilesLargerThanTheReadBuffer) {
  const auto path = tether::testing::scratch_dir() / "sha";
  const std::string data(3 * (1 << 20) + 17, 'a');
  std::ofstream(path, std::ios::binary) << data;
  EXPECT_EQ(sha256_file_hex(path.string()), sha256_hex(data));
  EXPECT_EQ(git_blob_sha1_file_hex(path.string()), git_blob_sha1_hex(data));
  std::filesystem::remove(path);
  EXPECT_THROW(sha256_file_hex(path.string()), Error);
}

TEST(GitBlob, MatchesGitHashObject) {
  EXPECT_EQ(git_blob_sha1_hex("hello\n"), "ce013625030ba8dba906f756967f9e9ca394464a");
  EXPECT_EQ(git_blob_sha1_hex(""), "e69de29bb2d1d6434b8b29ae775ad8c2e48c5391");
  EXPECT_TRUE(is_sha1_hex("e69de29bb2d1d6434b8b29ae775ad8c2e48c5391"));
  EXPECT_FALSE(is_sha256_hex("E3B0"));
}
