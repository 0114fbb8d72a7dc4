// Integration tests: HubClient against fake_hub.py (a local hub + CDN on loopback). Covers the
// cache layout written, token handling across the CDN redirect, resume with Range, ETag
// verification, hub error responses, offline fallback and an unreachable endpoint.
#include <arpa/inet.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <sys/wait.h>

#include "core/json_util.h"
#include "hub/hash.h"
#include "hub/http.h"
#include "hub/hub_client.h"
#include "hub_test_util.h"

using namespace tether::hub;
using namespace tether::hub::test;

namespace {

const std::string kRepo = "tether-test/tiny";
const std::string kMain = "0123456789abcdef0123456789abcdef01234567";
const std::string kDev = "fedcba9876543210fedcba9876543210fedcba98";
const std::string kGoodToken = "hf_good_token";
const std::string kConfig = "{\"type\": \"smolvla\", \"chunk_size\": 50}\n";

// Runs fake_hub.py for one test; it exits when we close its stdin.
class FakeHub {
 public:
  FakeHub() {
    int in_pipe[2], out_pipe[2];
    if (::pipe(in_pipe) != 0 || ::pipe(out_pipe) != 0) throw std::runtime_error("pipe failed");
    pid_ = ::fork();
    if (pid_ == 0) {
      ::dup2(in_pipe[0], 0);
      ::dup2(out_pipe[1], 1);
      ::close(in_pipe[1]);
      ::close(out_pipe[0]);
      std::string script = std::string(TETHER_SOURCE_DIR) + "/tests/hub/fake_hub.py";
      ::execl(TETHER_PYTHON3, TETHER_PYTHON3, script.c_str(), static_cast<char*>(nullptr));
      ::_exit(127);
    }
    ::close(in_pipe[0]);
    ::close(out_pipe[1]);
    stdin_fd_ = in_pipe[1];
    std::string line;
    char c;
    while (::read(out_pipe[0], &c, 1) == 1 && c != '\n') line += c;
    ::close(out_pipe[0]);
    if (line.empty() || line[0] != '{')
      throw std::runtime_error("tests/hub/fake_hub.py did not start (python: " TETHER_PYTHON3 ")");
    auto j = tether::JsonMap::parse(line);
    hub_url_ = j.at("hub").get<std::string>();
    cdn_url_ = j.at("cdn").get<std::string>();
  }
  ~FakeHub() {
    ::close(stdin_fd_);
    int status = 0;
    ::waitpid(pid_, &status, 0);
  }
  const std::string& hub_url() const { return hub_url_; }
  const std::string& cdn_url() const { return cdn_url_; }

  // Every request the hub and the CDN received, oldest first.
  tether::JsonMap log() const {
    HttpClient http;
    HttpRequest req;
    req.url = hub_url_ + "/_log";
    auto res = http.perform(req);
    return tether::JsonMap::parse(res.response.body);
  }
  std::vector<tether::JsonMap> requests(const std::string& server,
                                        const std::string& path_part) const {
    std::vector<tether::JsonMap> out;
    for (const auto& r : log())
      if (r["server"] == server &&
          r["path"].get<std::string>().find(path_part) != std::string::npos)
        out.push_back(r);
    return out;
  }

 private:
  pid_t pid_ = -1;
  int stdin_fd_ = -1;
  std::string hub_url_, cdn_url_;
};

bool has_header(const tether::JsonMap& request, const std::string& name) {
  for (auto& [k, v] : request["headers"].items()) {
    std::string lower = k;
    for (auto& ch : lower) ch = static_cast<char>(std::tolower(static_cast<unsigned char>(ch)));
    if (lower == name) return true;
  }
  return false;
}

std::string header_value(const tether::JsonMap& request, const std::string& name) {
  for (auto& [k, v] : request["headers"].items())
    if (k == name) return v.get<std::string>();
  return "";
}

class IntegrationHub : public ::testing::Test {
 protected:
  void SetUp() override {
    // Loopback must never go through a proxy configured in the environment.
    ::setenv("NO_PROXY", "*", 1);
    ::setenv("no_proxy", "*", 1);
  }
  HubClient client(std::optional<std::string> token = std::nullopt, bool offline = false) {
    HubOptions opt;
    opt.endpoint = hub.hub_url();
    opt.cache_root = dir.str();
    opt.token = token;
    opt.offline = offline;
    opt.progress = ProgressMode::never;
    return HubClient(opt);
  }
  fs::path repo_dir() const { return dir.path() / "models--tether-test--tiny"; }

  FakeHub hub;
  ScratchDir dir{"download"};
};

template <typename F>
HubError hub_error_of(F&& f) {
  try {
    f();
  } catch (const HubError& e) {
    return e;
  }
  ADD_FAILURE() << "no HubError thrown";
  return HubError(HubErrorKind::server, "none");
}

}  // namespace

TEST_F(IntegrationHub, ResolveReturnsCommitAndFileList) {
  auto c = client();
  RepoInfo info = c.resolve(kRepo, "main");
  EXPECT_EQ(info.commit, kMain);
  EXPECT_FALSE(info.from_cache);
  std::vector<std::string> paths;
  for (auto& f : info.files) paths.push_back(f.path);
  EXPECT_EQ(paths,
            (std::vector<std::string>{"big.bin", "config.json", "corrupt.bin", "model.safetensors",
                                      "norange.bin", "sub/dir/notes.txt"}));
  EXPECT_EQ(c.resolve(kRepo, "dev").commit, kDev);
  EXPECT_TRUE(c.resolve("tether-test/gated").gated);
}

TEST_F(IntegrationHub, GitFileLandsInTheExactHuggingfaceHubLayout) {
  auto c = client();
  std::string p = c.download_file(kRepo, "config.json");
  std::string etag = git_blob_sha1_hex(kConfig);
  EXPECT_EQ(p, (repo_dir() / "snapshots" / kMain / "config.json").string());
  ASSERT_TRUE(fs::is_symlink(p));
  EXPECT_EQ(fs::read_symlink(p).string(), "../../blobs/" + etag);
  EXPECT_EQ(read_file(repo_dir() / "blobs" / etag), kConfig);
  EXPECT_EQ(read_file(repo_dir() / "refs" / "main"), kMain);
  EXPECT_TRUE(fs::exists(dir.path() / "CACHEDIR.TAG"));
  EXPECT_TRUE(fs::exists(dir.path() / ".locks" / "models--tether-test--tiny" / (etag + ".lock")));
  // Nothing left over: no partial files beside the blob.
  size_t blobs = 0;
  for (auto& e : fs::directory_iterator(repo_dir() / "blobs"))
    blobs += e.path().extension() != ".incomplete";
  EXPECT_EQ(blobs, 1u);

  std::string nested = c.download_file(kRepo, "sub/dir/notes.txt");
  EXPECT_EQ(fs::read_symlink(nested).string(),
            "../../../../blobs/" + git_blob_sha1_hex("nested file\n"));
  EXPECT_EQ(read_file(nested), "nested file\n");
}

TEST_F(IntegrationHub, LfsFileComesFromTheCdnWithoutTheToken) {
  auto c = client(kGoodToken);
  std::string weights = pattern_bytes(300 * 1024, 1);
  std::string sha = sha256_hex(weights);
  std::string p = c.download_file(kRepo, "model.safetensors");
  EXPECT_EQ(read_file(p), weights);
  EXPECT_EQ(fs::read_symlink(p).string(),
            "../../blobs/" + sha);  // named by X-Linked-Etag, not the ETag

  auto head = hub.requests("hub", "/resolve/main/model.safetensors");
  ASSERT_EQ(head.size(), 1u);
  EXPECT_EQ(head[0]["method"], "HEAD");
  EXPECT_EQ(header_value(head[0], "Authorization"), "Bearer " + kGoodToken);
  auto cdn = hub.requests("cdn", sha);
  ASSERT_EQ(cdn.size(), 1u);
  EXPECT_EQ(cdn[0]["method"], "GET");
  EXPECT_FALSE(has_header(cdn[0], "authorization")) << cdn[0].dump();
}

TEST_F(IntegrationHub, SecondDownloadIsServedFromTheCacheAfterOneHead) {
  auto c = client();
  std::string first = c.download_file(kRepo, "model.safetensors");
  std::string again = c.download_file(kRepo, "model.safetensors");
  EXPECT_EQ(first, again);
  EXPECT_EQ(hub.requests("cdn", "/repos/").size(), 1u);  // the bytes were fetched once
  // Pinned to a commit, a cached file needs no request at all.
  size_t before = hub.log().size();
  c.download_file(kRepo, "model.safetensors", kMain);
  EXPECT_EQ(hub.log().size(), before);
}

TEST_F(IntegrationHub, CutTransferIsResumedWithRange) {
  auto c = client();
  std::string big = pattern_bytes(1024 * 1024, 2);
  std::string p = c.download_file(kRepo, "big.bin");
  EXPECT_EQ(read_file(p), big);
  auto cdn = hub.requests("cdn", sha256_hex(big));
  ASSERT_EQ(cdn.size(), 2u);
  EXPECT_FALSE(has_header(cdn[0], "range"));
  EXPECT_EQ(header_value(cdn[1], "Range"), "bytes=262144-");
  EXPECT_FALSE(fs::exists(repo_dir() / "blobs" / (sha256_hex(big) + ".incomplete")));
}

TEST_F(IntegrationHub, PartialFileFromAnEarlierRunIsResumed) {
  std::string weights = pattern_bytes(300 * 1024, 1);
  std::string sha = sha256_hex(weights);
  write_file(repo_dir() / "blobs" / (sha + ".incomplete"), weights.substr(0, 100000));
  auto c = client();
  EXPECT_EQ(read_file(c.download_file(kRepo, "model.safetensors")), weights);
  auto cdn = hub.requests("cdn", sha);
  ASSERT_EQ(cdn.size(), 1u);
  EXPECT_EQ(header_value(cdn[0], "Range"), "bytes=100000-");
}

TEST_F(IntegrationHub, ServerIgnoringRangeRestartsTheFileFromZero) {
  std::string data = pattern_bytes(48 * 1024, 4);
  std::string sha = sha256_hex(data);
  write_file(repo_dir() / "blobs" / (sha + ".incomplete"),
             std::string(1000, 'x'));  // would poison an append
  auto c = client();
  EXPECT_EQ(read_file(c.download_file(kRepo, "norange.bin")), data);
  auto cdn = hub.requests("cdn", sha);
  ASSERT_EQ(cdn.size(), 1u);
  EXPECT_EQ(header_value(cdn[0], "Range"), "bytes=1000-");
}

TEST_F(IntegrationHub, ProgressGoesToStderrOnlyWhenAskedOrOnATerminal) {
  HubOptions opt;
  opt.endpoint = hub.hub_url();
  opt.cache_root = dir.str();
  opt.progress = ProgressMode::always;
  HubClient loud(opt);
  ::testing::internal::CaptureStderr();
  loud.download_file(kRepo, "model.safetensors");
  std::string drawn = ::testing::internal::GetCapturedStderr();
  EXPECT_NE(drawn.find("model.safetensors"), std::string::npos) << drawn;
  EXPECT_NE(drawn.find("100%"), std::string::npos) << drawn;

  opt.progress = ProgressMode::automatic;  // stderr is captured into a file here: not a terminal
  HubClient quiet(opt);
  ::testing::internal::CaptureStderr();
  quiet.download_file(kRepo, "big.bin");
  EXPECT_EQ(::testing::internal::GetCapturedStderr(), "");
}

TEST_F(IntegrationHub, HashMismatchDeletesThePartialFile) {
  auto c = client();
  HubError e = hub_error_of([&] { c.download_file(kRepo, "corrupt.bin"); });
  EXPECT_EQ(e.kind(), HubErrorKind::corrupt);
  EXPECT_EQ(e.code(), tether::ErrorCode::format);
  std::string msg = e.what();
  EXPECT_NE(msg.find("sha256"), std::string::npos) << msg;
  EXPECT_NE(msg.find("corrupt.bin"), std::string::npos) << msg;
  std::string sha = sha256_hex(pattern_bytes(64 * 1024, 3));
  EXPECT_FALSE(fs::exists(repo_dir() / "blobs" / (sha + ".incomplete")));
  EXPECT_FALSE(fs::exists(repo_dir() / "blobs" / sha));
  EXPECT_FALSE(fs::exists(repo_dir() / "snapshots" / kMain / "corrupt.bin"));
}

TEST_F(IntegrationHub, GatedRepoNeedsTheRightToken) {
  {
    auto c = client();
    HubError e = hub_error_of([&] { c.download_file("tether-test/gated", "config.json"); });
    EXPECT_EQ(e.kind(), HubErrorKind::gated);
    std::string msg = e.what();
    EXPECT_NE(msg.find("HF_TOKEN"), std::string::npos) << msg;
    EXPECT_NE(msg.find("license"), std::string::npos) << msg;
    EXPECT_NE(msg.find("401"), std::string::npos) << msg;
    EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
  }
  {
    auto c = client(std::string("hf_wrong"));
    HubError e = hub_error_of([&] { c.download_file("tether-test/gated", "config.json"); });
    EXPECT_EQ(e.kind(), HubErrorKind::gated);
    EXPECT_NE(std::string(e.what()).find("403"), std::string::npos) << e.what();
  }
  auto c = client(kGoodToken);
  EXPECT_EQ(read_file(c.download_file("tether-test/gated", "config.json")), kConfig);
}

TEST_F(IntegrationHub, MissingFileRepoAndRevisionAreNotFound) {
  auto c = client();
  HubError file = hub_error_of([&] { c.download_file(kRepo, "nope.json"); });
  EXPECT_EQ(file.kind(), HubErrorKind::entry_not_found);
  EXPECT_EQ(file.code(), tether::ErrorCode::not_found);
  EXPECT_NE(std::string(file.what()).find("nope.json"), std::string::npos);
  EXPECT_EQ(hub_error_of([&] { c.download_file("tether-test/absent", "config.json"); }).kind(),
            HubErrorKind::repo_not_found);
  EXPECT_EQ(hub_error_of([&] { c.resolve("tether-test/absent"); }).kind(),
            HubErrorKind::repo_not_found);
  EXPECT_EQ(hub_error_of([&] { c.resolve(kRepo, "no-such-branch"); }).kind(),
            HubErrorKind::revision_not_found);
  EXPECT_EQ(hub_error_of([&] { c.download_file(kRepo, "config.json", "no-such-branch"); }).kind(),
            HubErrorKind::revision_not_found);
}

TEST_F(IntegrationHub, RenamedRepoRedirectOnTheHubKeepsTheToken) {
  auto c = client(kGoodToken);
  std::string p = c.download_file("tether-test/old-name", "config.json");
  EXPECT_EQ(read_file(p), kConfig);
  // Cached under the name that was asked for, as huggingface_hub does.
  EXPECT_NE(p.find("models--tether-test--old-name"), std::string::npos);
  auto followed = hub.requests("hub", "/tether-test/tiny/resolve/main/config.json");
  ASSERT_EQ(followed.size(), 2u);  // the HEAD after the redirect, then the GET
  EXPECT_EQ(header_value(followed[0], "Authorization"), "Bearer " + kGoodToken);
}

TEST_F(IntegrationHub, SnapshotDownloadFiltersWritesRefsAndWorksOfflineAfterwards) {
  auto c = client();
  std::string snap = c.snapshot_download(kRepo, "dev", {"*.json", "sub/"});
  EXPECT_EQ(snap, (repo_dir() / "snapshots" / kDev).string());
  EXPECT_EQ(read_file(repo_dir() / "refs" / "dev"), kDev);
  EXPECT_EQ(read_file(fs::path(snap) / "config.json"),
            "{\"type\": \"smolvla\", \"chunk_size\": 10}\n");
  EXPECT_TRUE(fs::exists(fs::path(snap) / "sub" / "dir" / "notes.txt"));
  EXPECT_FALSE(fs::exists(fs::path(snap) / "model.safetensors"));
  EXPECT_TRUE(hub.requests("cdn", "/repos/").empty());

  auto offline = client(std::nullopt, true);
  size_t before = hub.log().size();
  EXPECT_EQ(offline.snapshot_download(kRepo, "dev", {"*.json"}), snap);
  EXPECT_EQ(read_file(offline.download_file(kRepo, "config.json", "dev")),
            "{\"type\": \"smolvla\", \"chunk_size\": 10}\n");
  EXPECT_EQ(offline.cached_snapshot(kRepo, "dev").value_or(""), snap);
  EXPECT_EQ(hub.log().size(), before);  // offline means no request at all
  EXPECT_EQ(hub_error_of([&] { offline.download_file(kRepo, "config.json", "main"); }).kind(),
            HubErrorKind::not_cached);
}

TEST_F(IntegrationHub, FullSnapshotMatchesTheHubAndUnreachableHubFallsBackToTheCache) {
  auto c = client();
  std::string snap =
      c.snapshot_download(kRepo, "main", {"config.json", "model.safetensors", "sub/*"});
  EXPECT_EQ(read_file(fs::path(snap) / "model.safetensors"), pattern_bytes(300 * 1024, 1));

  // Same cache, endpoint on a closed port: cached files still resolve, like huggingface_hub does.
  HubOptions opt;
  opt.endpoint = "http://127.0.0.1:1";
  opt.cache_root = dir.str();
  opt.progress = ProgressMode::never;
  HubClient unreachable(opt);
  EXPECT_EQ(unreachable.download_file(kRepo, "config.json"),
            (fs::path(snap) / "config.json").string());
  RepoInfo info = unreachable.resolve(kRepo);
  EXPECT_TRUE(info.from_cache);
  EXPECT_EQ(info.commit, kMain);
}

namespace {

// A Python with huggingface_hub: TETHER_HF_PYTHON, else the oracle venv (tools/oracle/setup.sh
// creates it).
std::optional<std::string> huggingface_hub_python() {
  std::string py;
  if (const char* v = std::getenv("TETHER_HF_PYTHON")) {
    py = v;
  } else {
    const char* cache = std::getenv("TETHER_CACHE");
    const char* home = std::getenv("HOME");
    py = cache ? std::string(cache) : std::string(home ? home : "") + "/.cache/tether";
    py += "/oracle/venv/bin/python";
  }
  if (!fs::exists(py)) return std::nullopt;
  std::string probe = "'" + py + "' -c 'import huggingface_hub' >/dev/null 2>&1";
  if (std::system(probe.c_str()) != 0) return std::nullopt;
  return py;
}

// Runs hf_crosscheck.py and returns its JSON report.
tether::JsonMap run_crosscheck(const std::string& python, const std::string& env,
                               const std::string& cache_dir, const std::string& repo,
                               const std::string& revision, const std::vector<std::string>& files,
                               const fs::path& scratch) {
  std::string cmd = env + " '" + python + "' '" + TETHER_SOURCE_DIR +
                    "/tests/hub/hf_crosscheck.py' '" + cache_dir + "' '" + repo + "' '" + revision +
                    "'";
  for (const auto& f : files) cmd += " '" + f + "'";
  fs::path out = scratch / "crosscheck.json";
  cmd += " > '" + out.string() + "' 2> '" + (scratch / "crosscheck.err").string() + "'";
  int rc = std::system(cmd.c_str());
  EXPECT_EQ(rc, 0) << cmd << "\n" << read_file(scratch / "crosscheck.err");
  if (rc != 0) return tether::JsonMap::object();
  return tether::JsonMap::parse(read_file(out));
}

}  // namespace

TEST_F(IntegrationHub, HuggingfaceHubAndTetherShareOneCache) {
  auto python = huggingface_hub_python();
  if (!python)
    GTEST_SKIP()
        << "no Python with huggingface_hub (set TETHER_HF_PYTHON or run tools/oracle/setup.sh)";
  ScratchDir scratch("crosscheck");
  std::string quiet =
      "HF_HUB_DISABLE_TELEMETRY=1 HF_HUB_DISABLE_PROGRESS_BARS=1 NO_PROXY='*' HF_TOKEN= ";

  // Python downloads from the fake hub; Tether, offline, finds the very same files.
  auto py = run_crosscheck(*python, quiet + "HF_ENDPOINT=" + hub.hub_url(), dir.str(), kRepo,
                           "main", {"config.json", "model.safetensors"}, scratch.path());
  ASSERT_TRUE(py.contains("paths"));
  size_t requests_by_python = hub.log().size();
  auto offline = client(std::nullopt, true);
  EXPECT_EQ(offline.download_file(kRepo, "config.json"), py["paths"][0].get<std::string>());
  EXPECT_EQ(offline.download_file(kRepo, "model.safetensors"), py["paths"][1].get<std::string>());

  // Tether downloads more (a nested git file, another branch); Python, offline, finds them, and its
  // cache scanner sees one consistent cache.
  auto online = client();
  std::string nested = online.download_file(kRepo, "sub/dir/notes.txt");
  std::string dev_config = online.download_file(kRepo, "config.json", "dev");
  EXPECT_GT(hub.log().size(), requests_by_python);
  auto main_check =
      run_crosscheck(*python, quiet + "HF_HUB_OFFLINE=1 HF_ENDPOINT=http://127.0.0.1:1", dir.str(),
                     kRepo, "main", {"sub/dir/notes.txt", "model.safetensors"}, scratch.path());
  ASSERT_TRUE(main_check.contains("paths"));
  EXPECT_EQ(main_check["paths"][0].get<std::string>(), nested);
  auto dev_check =
      run_crosscheck(*python, quiet + "HF_HUB_OFFLINE=1 HF_ENDPOINT=http://127.0.0.1:1", dir.str(),
                     kRepo, "dev", {"config.json"}, scratch.path());
  ASSERT_TRUE(dev_check.contains("paths"));
  EXPECT_EQ(dev_check["paths"][0].get<std::string>(), dev_config);
  EXPECT_TRUE(dev_check["warnings"].empty()) << dev_check["warnings"].dump();
  auto expected = tether::JsonMap::array();
  auto blob = [&](const std::string& etag) { return (repo_dir() / "blobs" / etag).string(); };
  expected.push_back({kMain, "config.json", blob(git_blob_sha1_hex(kConfig))});
  expected.push_back({kMain, "model.safetensors", blob(sha256_hex(pattern_bytes(300 * 1024, 1)))});
  expected.push_back({kMain, "sub/dir/notes.txt", blob(git_blob_sha1_hex("nested file\n"))});
  expected.push_back({kDev, "config.json",
                      blob(git_blob_sha1_hex("{\"type\": \"smolvla\", \"chunk_size\": 10}\n"))});
  std::sort(expected.begin(), expected.end());
  EXPECT_EQ(dev_check["cached"], expected);
}

TEST(IntegrationNoNetwork, ClosedPortGivesANetworkErrorNamingOfflineMode) {
  // Bind then close a port so that nothing listens there.
  int s = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(::bind(s, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)), 0);
  socklen_t len = sizeof(addr);
  ::getsockname(s, reinterpret_cast<sockaddr*>(&addr), &len);
  int port = ntohs(addr.sin_port);
  ::close(s);

  ScratchDir dir("no_network");
  HubOptions opt;
  opt.endpoint = "http://127.0.0.1:" + std::to_string(port);
  opt.cache_root = dir.str();
  opt.progress = ProgressMode::never;
  HubClient c(opt);
  for (int which = 0; which < 3; ++which) {
    try {
      if (which == 0) c.download_file("org/model", "config.json");
      if (which == 1) c.resolve("org/model");
      if (which == 2) c.snapshot_download("org/model");
      ADD_FAILURE() << "expected a network error";
    } catch (const HubError& e) {
      EXPECT_EQ(e.kind(), HubErrorKind::network);
      EXPECT_EQ(e.code(), tether::ErrorCode::io);
      std::string msg = e.what();
      EXPECT_NE(msg.find("HF_HUB_OFFLINE=1"), std::string::npos) << msg;
      EXPECT_NE(msg.find("127.0.0.1:" + std::to_string(port)), std::string::npos) << msg;
      EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
    }
  }
}
