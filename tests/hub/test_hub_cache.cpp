// Unit tests: digests, patterns, ids, environment, and the cache layout shared with huggingface_hub
// (including a cache built by hand the way huggingface_hub builds it, read back offline).
#include <gtest/gtest.h>

#include "hub/cache.h"
#include "hub/hash.h"
#include "hub/hub_client.h"
#include "hub_test_util.h"

using namespace tether::hub;
using namespace tether::hub::test;

namespace {

const std::string kCommit = "0123456789abcdef0123456789abcdef01234567";

template <typename F>
HubErrorKind error_kind_of(F&& f) {
  try {
    f();
  } catch (const HubError& e) {
    return e.kind();
  }
  ADD_FAILURE() << "no HubError thrown";
  return HubErrorKind::server;
}

// Lays out one repo exactly as huggingface_hub's hf_hub_download leaves it: blobs named by ETag,
// relative snapshot symlinks, and a bare commit hash in refs/main.
void build_python_style_cache(const fs::path& root, const std::string& config,
                              const std::string& weights) {
  fs::path repo = root / "models--lerobot--smolvla_base";
  std::string config_etag = git_blob_sha1_hex(config);
  std::string weights_etag = sha256_hex(weights);
  write_file(repo / "blobs" / config_etag, config);
  write_file(repo / "blobs" / weights_etag, weights);
  write_file(repo / "refs" / "main", kCommit);
  fs::path snap = repo / "snapshots" / kCommit;
  fs::create_directories(snap / "sub");
  fs::create_symlink("../../blobs/" + config_etag, snap / "config.json");
  fs::create_symlink("../../../blobs/" + weights_etag, snap / "sub" / "model.safetensors");
}

}  // namespace

TEST(HubHash, Sha256AndGitBlobIdsOfKnownContent) {
  EXPECT_EQ(sha256_hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  // `printf 'hello\n' | git hash-object --stdin`
  EXPECT_EQ(git_blob_sha1_hex("hello\n"), "ce013625030ba8dba906f756967f9e9ca394464a");
  EXPECT_EQ(git_blob_sha1_hex(""), "e69de29bb2d1d6434b8b29ae775ad8c2e48c5391");
}

TEST(HubHash, FileDigestsMatchInMemoryAndVerifyEtags) {
  ScratchDir dir("hash");
  std::string data = pattern_bytes(3 * 1024 * 1024 + 17, 7);  // spans several read buffers
  fs::path p = dir.path() / "f";
  write_file(p, data);
  EXPECT_EQ(sha256_file_hex(p.string()), sha256_hex(data));
  EXPECT_EQ(git_blob_sha1_file_hex(p.string()), git_blob_sha1_hex(data));

  EXPECT_TRUE(verify_file_against_etag(p.string(), sha256_hex(data)).ok);
  EXPECT_EQ(verify_file_against_etag(p.string(), sha256_hex(data)).algorithm, "sha256");
  EXPECT_TRUE(verify_file_against_etag(p.string(), git_blob_sha1_hex(data)).ok);
  auto bad = verify_file_against_etag(p.string(), sha256_hex("other"));
  EXPECT_TRUE(bad.checked);
  EXPECT_FALSE(bad.ok);
  auto other_form = verify_file_against_etag(p.string(), "xet-abc");
  EXPECT_FALSE(other_form.checked);
  EXPECT_TRUE(other_form.ok);
}

TEST(HubPatterns, FnmatchSemanticsLikeHuggingfaceHub) {
  EXPECT_TRUE(path_matches("model.safetensors", "*.safetensors"));
  EXPECT_TRUE(path_matches("sub/dir/model.safetensors", "*.safetensors"));  // '*' crosses '/'
  EXPECT_FALSE(path_matches("model.safetensors.index", "*.safetensors"));
  EXPECT_TRUE(path_matches("config.json", "config.jso?"));
  EXPECT_TRUE(path_matches("a1.bin", "a[0-9].bin"));
  EXPECT_FALSE(path_matches("a1.bin", "a[!0-9].bin"));
  EXPECT_TRUE(path_matches("tokenizer/vocab.json", "tokenizer/"));  // folder pattern
  EXPECT_FALSE(path_matches("Config.json", "config.json"));         // case-sensitive
  EXPECT_TRUE(path_matches_any("x", {}));
  EXPECT_FALSE(path_matches_any("x.txt", {"*.json", "*.bin"}));
}

TEST(HubIds, RepoIdsRevisionsAndPathsAreValidated) {
  EXPECT_NO_THROW(validate_repo_id("lerobot/smolvla_base"));
  EXPECT_NO_THROW(validate_repo_id("gpt2"));
  for (std::string bad : {"", "a/b/c", "a--b/c", "a/../b", "org/name.git", "-x/y", "org/na me"})
    EXPECT_EQ(error_kind_of([&] { validate_repo_id(bad); }), HubErrorKind::invalid) << bad;
  EXPECT_NO_THROW(validate_revision("refs/pr/1"));
  EXPECT_EQ(error_kind_of([] { validate_revision("../main"); }), HubErrorKind::invalid);
  EXPECT_NO_THROW(validate_repo_path("sub/dir/file.txt"));
  for (std::string bad : {"/etc/passwd", "a/../../b", "a//b", "dir/", "a\\b"})
    EXPECT_EQ(error_kind_of([&] { validate_repo_path(bad); }), HubErrorKind::invalid) << bad;
  EXPECT_EQ(repo_folder_name("lerobot/smolvla_base"), "models--lerobot--smolvla_base");
  EXPECT_EQ(repo_folder_name("gpt2"), "models--gpt2");
}

TEST(HubEnv, CacheRootFollowsHuggingfaceHubPrecedence) {
  ScopedEnv home("HOME", "/home/someone");
  ScopedEnv xdg("XDG_CACHE_HOME", std::nullopt);
  ScopedEnv legacy("HUGGINGFACE_HUB_CACHE", std::nullopt);
  {
    ScopedEnv hf_home("HF_HOME", std::nullopt);
    ScopedEnv hub_cache("HF_HUB_CACHE", std::nullopt);
    EXPECT_EQ(default_cache_root(), "/home/someone/.cache/huggingface/hub");
    ScopedEnv xdg2("XDG_CACHE_HOME", "/xdg");
    EXPECT_EQ(default_cache_root(), "/xdg/huggingface/hub");
  }
  {
    ScopedEnv hf_home("HF_HOME", "~/hf");
    ScopedEnv hub_cache("HF_HUB_CACHE", std::nullopt);
    EXPECT_EQ(default_cache_root(), "/home/someone/hf/hub");
    ScopedEnv hub_cache2("HF_HUB_CACHE", "/data/hub");
    EXPECT_EQ(default_cache_root(), "/data/hub");
  }
}

TEST(HubEnv, TokenFromEnvironmentOrTokenFileAndOfflineFlag) {
  ScratchDir dir("token");
  ScopedEnv hf_home("HF_HOME", dir.str());
  ScopedEnv token_path("HF_TOKEN_PATH", std::nullopt);
  ScopedEnv legacy("HUGGING_FACE_HUB_TOKEN", std::nullopt);
  {
    ScopedEnv token("HF_TOKEN", std::nullopt);
    EXPECT_FALSE(token_from_env().has_value());
    write_file(dir.path() / "token", "hf_from_file\n");
    EXPECT_EQ(token_from_env().value_or(""), "hf_from_file");
  }
  {
    ScopedEnv token("HF_TOKEN", "  hf_from_env ");
    EXPECT_EQ(token_from_env().value_or(""), "hf_from_env");
  }
  ScopedEnv transformers("TRANSFORMERS_OFFLINE", std::nullopt);
  for (auto [value, expected] :
       {std::pair{"1", true}, {"yes", true}, {"TRUE", true}, {"0", false}, {"", false}}) {
    ScopedEnv offline("HF_HUB_OFFLINE", std::string(value));
    EXPECT_EQ(offline_from_env(), expected) << value;
  }
}

TEST(HubEnv, ClientFromEnvironment) {
  ScratchDir dir("from_env");
  ScopedEnv endpoint("HF_ENDPOINT", "http://mirror.example:8080/");
  ScopedEnv cache("HF_HUB_CACHE", dir.str());
  ScopedEnv token("HF_TOKEN", "hf_abc");
  ScopedEnv offline("HF_HUB_OFFLINE", "1");
  ScopedEnv etag_timeout("HF_HUB_ETAG_TIMEOUT", "3");
  ScopedEnv download_timeout("HF_HUB_DOWNLOAD_TIMEOUT", "not a number");
  HubClient c = HubClient::from_env();
  EXPECT_EQ(c.options().endpoint, "http://mirror.example:8080");
  EXPECT_EQ(c.options().cache_root, dir.str());
  EXPECT_EQ(c.cache().root(), dir.str());
  EXPECT_EQ(c.options().token.value_or(""), "hf_abc");
  EXPECT_TRUE(c.options().offline);
  EXPECT_EQ(c.options().metadata_timeout_s, 3);
  EXPECT_EQ(c.options().stall_timeout_s, 10);
}

TEST(HubCacheLayout, PointersAreRelativeSymlinksIntoBlobsAndRefsHoldTheBareCommit) {
  ScratchDir dir("layout");
  HubCache cache(dir.str());
  std::string repo = "org/model";
  std::string etag = sha256_hex("weights");
  write_file(cache.blob_path(repo, etag), "weights");
  cache.link_pointer(repo, kCommit, "model.safetensors", etag);
  cache.link_pointer(repo, kCommit, "a/b/model.safetensors", etag);
  cache.write_ref(repo, "main", kCommit);
  cache.write_ref(repo, kCommit, kCommit);  // a commit is never written as a ref

  fs::path snap = dir.path() / "models--org--model" / "snapshots" / kCommit;
  ASSERT_TRUE(fs::is_symlink(snap / "model.safetensors"));
  EXPECT_EQ(fs::read_symlink(snap / "model.safetensors").string(), "../../blobs/" + etag);
  EXPECT_EQ(fs::read_symlink(snap / "a" / "b" / "model.safetensors").string(),
            "../../../../blobs/" + etag);
  EXPECT_EQ(read_file(snap / "a" / "b" / "model.safetensors"), "weights");
  EXPECT_EQ(read_file(dir.path() / "models--org--model" / "refs" / "main"), kCommit);  // no newline
  EXPECT_FALSE(fs::exists(dir.path() / "models--org--model" / "refs" / kCommit));
  EXPECT_EQ(cache.resolve_commit(repo, "main").value_or(""), kCommit);
  EXPECT_EQ(cache.snapshot_files(repo, kCommit),
            (std::vector<std::string>{"a/b/model.safetensors", "model.safetensors"}));
  // Re-linking replaces the pointer rather than failing on the existing one.
  EXPECT_NO_THROW(cache.link_pointer(repo, kCommit, "model.safetensors", etag));
}

TEST(HubOffline, ReusesACacheBuiltTheWayHuggingfaceHubBuildsIt) {
  ScratchDir dir("python_cache");
  std::string config = "{\"type\": \"smolvla\"}\n";
  std::string weights = pattern_bytes(4096, 5);
  build_python_style_cache(dir.path(), config, weights);
  // A trailing newline in a hand-edited ref is tolerated.
  write_file(dir.path() / "models--lerobot--smolvla_base" / "refs" / "v1", kCommit + "\n");

  HubOptions opt;
  opt.cache_root = dir.str();
  opt.offline = true;
  opt.endpoint = "http://127.0.0.1:9";  // never contacted: offline
  HubClient client(opt);

  std::string p = client.download_file("lerobot/smolvla_base", "sub/model.safetensors");
  EXPECT_EQ(p, (dir.path() / "models--lerobot--smolvla_base" / "snapshots" / kCommit / "sub" /
                "model.safetensors")
                   .string());
  EXPECT_EQ(read_file(p), weights);
  EXPECT_EQ(read_file(client.download_file("lerobot/smolvla_base", "config.json", "v1")), config);
  EXPECT_EQ(read_file(client.download_file("lerobot/smolvla_base", "config.json", kCommit)),
            config);

  RepoInfo info = client.resolve("lerobot/smolvla_base", "main");
  EXPECT_TRUE(info.from_cache);
  EXPECT_EQ(info.commit, kCommit);
  ASSERT_EQ(info.files.size(), 2u);
  EXPECT_EQ(info.files[0].path, "config.json");
  EXPECT_EQ(info.files[1].path, "sub/model.safetensors");

  std::string snap = client.snapshot_download("lerobot/smolvla_base", "main", {"*.safetensors"});
  EXPECT_EQ(snap, client.cached_snapshot("lerobot/smolvla_base").value_or(""));
  EXPECT_EQ(read_file(fs::path(snap) / "config.json"), config);
}

TEST(HubOffline, MissingEntriesFailClearlyWithoutNetwork) {
  ScratchDir dir("offline_miss");
  build_python_style_cache(dir.path(), "{}", "w");
  HubOptions opt;
  opt.cache_root = dir.str();
  opt.offline = true;
  opt.endpoint = "http://127.0.0.1:9";
  HubClient client(opt);
  try {
    client.download_file("lerobot/smolvla_base", "absent.json");
    FAIL() << "expected a not_cached error";
  } catch (const HubError& e) {
    EXPECT_EQ(e.kind(), HubErrorKind::not_cached);
    EXPECT_EQ(e.code(), tether::ErrorCode::not_found);
    std::string msg = e.what();
    EXPECT_NE(msg.find("HF_HUB_OFFLINE"), std::string::npos) << msg;
    EXPECT_NE(msg.find("absent.json"), std::string::npos) << msg;
    EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
  }
  EXPECT_EQ(error_kind_of([&] { client.resolve("lerobot/other"); }), HubErrorKind::not_cached);
  EXPECT_EQ(
      error_kind_of([&] { client.snapshot_download("lerobot/smolvla_base", "main", {"*.bin"}); }),
      HubErrorKind::not_cached);
  EXPECT_EQ(
      error_kind_of([&] { client.download_file("lerobot/smolvla_base", "config.json", "dev"); }),
      HubErrorKind::not_cached);
  EXPECT_FALSE(client.cached_snapshot("lerobot/smolvla_base", "dev").has_value());
}
