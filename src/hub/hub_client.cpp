// HubClient: the HEAD-then-GET download protocol of the Hugging Face Hub, written into the shared
// cache.
#include "hub/hub_client.h"

#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <thread>
#include <variant>

#include "core/json_util.h"
#include "hub/hash.h"
#include "hub/http.h"

namespace fs = std::filesystem;

namespace tether::hub {
namespace {

constexpr int kMaxRedirects = 20;

std::string env_or_empty(const char* name) {
  const char* v = std::getenv(name);
  return v ? std::string(v) : std::string();
}

std::string strip(const std::string& s) {
  size_t b = s.find_first_not_of(" \t\r\n");
  if (b == std::string::npos) return {};
  size_t e = s.find_last_not_of(" \t\r\n");
  return s.substr(b, e - b + 1);
}

long env_seconds(const char* name, long fallback) {
  std::string v = env_or_empty(name);
  if (v.empty()) return fallback;
  char* end = nullptr;
  double d = std::strtod(v.c_str(), &end);
  if (end == v.c_str() || d <= 0) return fallback;
  return std::max(1L, static_cast<long>(d + 0.5));
}

// W/"abc" and "abc" both become abc: the form used as the blob's file name.
std::string normalize_etag(std::string etag) {
  if (etag.rfind("W/", 0) == 0) etag = etag.substr(2);
  if (etag.size() >= 2 && etag.front() == '"' && etag.back() == '"')
    etag = etag.substr(1, etag.size() - 2);
  return etag;
}

std::optional<uint64_t> parse_size(const std::optional<std::string>& v) {
  if (!v || v->empty()) return std::nullopt;
  char* end = nullptr;
  unsigned long long n = std::strtoull(v->c_str(), &end, 10);
  if (*end != '\0') return std::nullopt;
  return static_cast<uint64_t>(n);
}

bool fnmatch_at(const std::string& s, size_t si, const std::string& p, size_t pi) {
  while (pi < p.size()) {
    char c = p[pi];
    if (c == '*') {
      while (pi < p.size() && p[pi] == '*') ++pi;
      if (pi == p.size()) return true;
      for (size_t k = si; k <= s.size(); ++k)
        if (fnmatch_at(s, k, p, pi)) return true;
      return false;
    }
    if (si == s.size()) return false;
    if (c == '?') {
      ++si, ++pi;
      continue;
    }
    if (c == '[') {
      size_t j = pi + 1;
      bool negate = j < p.size() && p[j] == '!';
      if (negate) ++j;
      size_t start = j;
      if (j < p.size() && p[j] == ']') ++j;  // a leading ']' is a literal member
      while (j < p.size() && p[j] != ']') ++j;
      if (j < p.size()) {
        bool hit = false;
        for (size_t k = start; k < j; ++k) {
          if (k + 2 < j && p[k + 1] == '-') {
            hit = hit || (p[k] <= s[si] && s[si] <= p[k + 2]);
            k += 2;
          } else {
            hit = hit || p[k] == s[si];
          }
        }
        if (hit == negate) return false;
        ++si, pi = j + 1;
        continue;
      }
      // No closing ']': the '[' is literal, as in fnmatch.
    }
    if (c != s[si]) return false;
    ++si, ++pi;
  }
  return si == s.size();
}

struct FileMetadata {
  std::string commit;
  std::string etag;
  std::string location;  // where to GET the bytes (the CDN for LFS files)
  std::optional<uint64_t> size;
};

// A metadata call that failed: whether the cache may still answer, and the error to raise if not.
struct MetadataFailure {
  bool cache_may_answer = false;
  HubErrorKind kind = HubErrorKind::server;
  std::string message;
};

bool stderr_is_terminal() { return ::isatty(STDERR_FILENO) == 1; }

class ProgressBar {
 public:
  ProgressBar(bool enabled, std::string name, std::optional<uint64_t> total, uint64_t initial)
      : enabled_(enabled), name_(std::move(name)), total_(total), done_(initial) {
    if (name_.size() > 40) name_ = "..." + name_.substr(name_.size() - 37);
  }
  ~ProgressBar() {
    if (enabled_ && drawn_) std::fputc('\n', stderr);
  }
  void reset(uint64_t done) { done_ = done; }
  void add(uint64_t n) {
    done_ += n;
    if (!enabled_) return;
    auto now = std::chrono::steady_clock::now();
    if (drawn_ && now - last_ < std::chrono::milliseconds(100) && !(total_ && done_ == *total_))
      return;
    last_ = now;
    drawn_ = true;
    double mb = 1024.0 * 1024.0;
    if (total_ && *total_ > 0)
      std::fprintf(stderr, "\r%-40s %8.1f / %.1f MiB %3d%%", name_.c_str(), done_ / mb,
                   *total_ / mb, static_cast<int>(100.0 * done_ / *total_));
    else
      std::fprintf(stderr, "\r%-40s %8.1f MiB", name_.c_str(), done_ / mb);
    std::fflush(stderr);
  }

 private:
  bool enabled_;
  std::string name_;
  std::optional<uint64_t> total_;
  uint64_t done_;
  bool drawn_ = false;
  std::chrono::steady_clock::time_point last_{};
};

}  // namespace

std::optional<std::string> token_from_env() {
  for (const char* name : {"HF_TOKEN", "HUGGING_FACE_HUB_TOKEN"}) {
    std::string v = strip(env_or_empty(name));
    if (!v.empty()) return v;
  }
  std::string path = env_or_empty("HF_TOKEN_PATH");
  if (path.empty()) path = default_hf_home() + "/token";
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  std::string v =
      strip(std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>()));
  if (v.empty()) return std::nullopt;
  return v;
}

bool offline_from_env() {
  for (const char* name : {"HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"}) {
    std::string v = env_or_empty(name);
    std::transform(v.begin(), v.end(), v.begin(), [](unsigned char c) { return std::toupper(c); });
    if (v == "1" || v == "ON" || v == "YES" || v == "TRUE") return true;
  }
  return false;
}

bool path_matches(const std::string& path, const std::string& pattern) {
  std::string p = pattern;
  if (!p.empty() && p.back() == '/') p += '*';
  return fnmatch_at(path, 0, p, 0);
}

bool path_matches_any(const std::string& path, const std::vector<std::string>& patterns) {
  if (patterns.empty()) return true;
  return std::any_of(patterns.begin(), patterns.end(),
                     [&](const std::string& p) { return path_matches(path, p); });
}

struct HubClient::Net {
  HttpClient http;
};

HubClient::HubClient(HubOptions options)
    : options_(std::move(options)),
      cache_(options_.cache_root.empty() ? default_cache_root() : options_.cache_root),
      net_(std::make_unique<Net>()) {
  while (!options_.endpoint.empty() && options_.endpoint.back() == '/')
    options_.endpoint.pop_back();
  options_.cache_root = cache_.root();
}

HubClient::~HubClient() = default;
HubClient::HubClient(HubClient&&) noexcept = default;
HubClient& HubClient::operator=(HubClient&&) noexcept = default;

HubClient HubClient::from_env() {
  HubOptions o;
  std::string endpoint = env_or_empty("HF_ENDPOINT");
  if (!endpoint.empty()) o.endpoint = endpoint;
  o.cache_root = default_cache_root();
  o.token = token_from_env();
  o.offline = offline_from_env();
  o.metadata_timeout_s = env_seconds("HF_HUB_ETAG_TIMEOUT", o.metadata_timeout_s);
  o.stall_timeout_s = env_seconds("HF_HUB_DOWNLOAD_TIMEOUT", o.stall_timeout_s);
  return HubClient(std::move(o));
}

namespace {

// Hosts the token may travel to: the endpoint itself (same scheme, host and port) and the public
// hub's names.
bool is_hub_url(const std::string& url, const std::string& endpoint) {
  if (url_origin(url) == url_origin(endpoint)) return true;
  std::string host = url_host(url);
  return url.rfind("https://", 0) == 0 && (host == "huggingface.co" || host == "hf.co");
}

std::string describe_repo(const std::string& repo_id, const std::string& revision) {
  return "'" + repo_id + "' (revision '" + revision + "')";
}

// Turns a hub error response into a HubError kind and a one-line message.
MetadataFailure http_failure(const HttpResponse& r, const std::string& url,
                             const std::string& endpoint, const std::string& repo_id,
                             const std::string& revision, const std::optional<std::string>& file,
                             bool have_token) {
  MetadataFailure f;
  std::string code = r.header("X-Error-Code").value_or("");
  std::string server_msg = r.header("X-Error-Message").value_or("");
  std::string status = "HTTP " + std::to_string(r.status);
  std::string what = file ? "'" + *file + "' in " + describe_repo(repo_id, revision)
                          : describe_repo(repo_id, revision);
  std::string repo_page = endpoint + "/" + repo_id;
  if (code == "RevisionNotFound") {
    f.kind = HubErrorKind::revision_not_found;
    f.message = "revision '" + revision + "' not found in repo '" + repo_id + "' (" + status + ")";
  } else if (code == "EntryNotFound" || (r.status == 404 && file && code.empty())) {
    f.kind = HubErrorKind::entry_not_found;
    f.message = "file " + what + " not found on the hub (" + status + ")";
  } else if (code == "GatedRepo" ||
             ((r.status == 401 || r.status == 403) && code != "RepoNotFound")) {
    f.kind = HubErrorKind::gated;
    f.cache_may_answer = true;
    f.message =
        what + ": access denied (" + status + ", gated or private repo); " +
        (have_token
             ? "the token in HF_TOKEN has no access: accept the license at " + repo_page +
                   " with that account, or use another token"
             : "set HF_TOKEN to a token of an account that accepted the license at " + repo_page);
  } else if (code == "RepoNotFound" || r.status == 404) {
    f.kind = HubErrorKind::repo_not_found;
    f.cache_may_answer = true;
    f.message = "repo '" + repo_id + "' not found at " + endpoint + " (" + status + ")" +
                (have_token ? "; check the id and that HF_TOKEN can see it"
                            : "; check the id, or set HF_TOKEN if it is private or gated");
  } else {
    f.kind = HubErrorKind::server;
    f.cache_may_answer = true;
    f.message = what + ": " + status + " from " + url;
  }
  if (!server_msg.empty()) f.message += " (hub says: " + server_msg + ")";
  return f;
}

MetadataFailure transport_failure(const HttpResult& res, const std::string& url) {
  MetadataFailure f;
  f.cache_may_answer = true;
  f.kind = HubErrorKind::network;
  f.message = "cannot reach " + url_origin(url) + " (" + res.error + ")";
  return f;
}

}  // namespace

namespace {

// The operations of one HubClient call, with the client's options, cache and connection at hand.
class Session {
 public:
  Session(const HubOptions& o, const HubCache& c, HttpClient& h) : opt_(o), cache_(c), http_(h) {}

  std::vector<std::string> auth_headers(const std::string& url) const {
    std::vector<std::string> h;
    if (opt_.token && is_hub_url(url, opt_.endpoint))
      h.push_back("Authorization: Bearer " + *opt_.token);
    return h;
  }

  std::string cache_hint() const { return "cache at " + cache_.root(); }

  // HEAD on /resolve/, following redirects that stay on the hub (a renamed repo) and stopping at
  // one that leaves it: the LFS metadata is on that redirect response, and the token must not
  // follow it.
  std::variant<FileMetadata, MetadataFailure> file_metadata(const std::string& repo_id,
                                                            const std::string& path,
                                                            const std::string& revision) {
    std::string url = opt_.endpoint + "/" + repo_id + "/resolve/" + url_quote(revision, false) +
                      "/" + url_quote(path, true);
    HttpResult res;
    for (int hop = 0;; ++hop) {
      HttpRequest req;
      req.method = "HEAD";
      req.url = url;
      req.headers = auth_headers(url);
      // The size read from this response must be the file's, not that of a compressed body.
      req.headers.push_back("Accept-Encoding: identity");
      req.connect_timeout_s = opt_.metadata_timeout_s;
      req.timeout_s = opt_.metadata_timeout_s;
      res = http_.perform(req);
      if (res.failure != TransportFailure::none) return transport_failure(res, url);
      const HttpResponse& r = res.response;
      if (r.status >= 400)
        return http_failure(r, url, opt_.endpoint, repo_id, revision, path, opt_.token.has_value());
      if (!r.is_redirect()) break;
      std::string target = url_join(url, *r.header("Location"));
      if (!is_hub_url(target, opt_.endpoint) || hop + 1 >= kMaxRedirects) break;
      url = target;
    }
    const HttpResponse& r = res.response;
    FileMetadata m;
    m.commit = r.header("X-Repo-Commit").value_or("");
    if (!is_sha1_hex(m.commit)) {
      // It names a cache folder, so anything but a commit hash is refused.
      MetadataFailure f;
      f.cache_may_answer = true;
      f.message = url + " answered without a valid X-Repo-Commit header: HF_ENDPOINT (" +
                  opt_.endpoint +
                  ") does not look like a Hugging Face hub, or a proxy rewrote the response";
      return f;
    }
    m.etag = normalize_etag(r.header("X-Linked-Etag").value_or(r.header("ETag").value_or("")));
    if (m.etag.empty() || m.etag.find('/') != std::string::npos || m.etag == "." ||
        m.etag == "..") {
      MetadataFailure f;
      f.cache_may_answer = true;
      f.message = url + " answered without a usable ETag, so the file cannot be cached or verified";
      return f;
    }
    auto location = r.header("Location");
    m.location = location ? url_join(url, *location) : url;
    m.size = parse_size(r.header("X-Linked-Size"));
    if (!m.size && !r.is_redirect()) m.size = parse_size(r.header("Content-Length"));
    return m;
  }

  // The cached pointer for (revision, path), if refs/ and snapshots/ have it.
  std::optional<std::string> cached_pointer(const std::string& repo_id, const std::string& path,
                                            const std::string& revision) const {
    auto commit = cache_.resolve_commit(repo_id, revision);
    if (!commit) return std::nullopt;
    std::string pointer = cache_.pointer_path(repo_id, *commit, path);
    std::error_code ec;
    if (!fs::exists(pointer, ec)) return std::nullopt;
    return pointer;
  }

  std::string download_file(const std::string& repo_id, const std::string& path,
                            const std::string& revision) {
    validate_repo_id(repo_id);
    validate_repo_path(path);
    validate_revision(revision);
    std::string what = "'" + path + "' of " + describe_repo(repo_id, revision);
    // A commit-pinned file already in the cache needs no network at all.
    if (is_sha1_hex(revision))
      if (auto p = cached_pointer(repo_id, path, revision)) return *p;
    if (opt_.offline) {
      if (auto p = cached_pointer(repo_id, path, revision)) return *p;
      throw HubError(HubErrorKind::not_cached,
                     "HF_HUB_OFFLINE is set and " + what + " is not in the " + cache_hint());
    }
    auto meta_or_fail = file_metadata(repo_id, path, revision);
    if (auto* f = std::get_if<MetadataFailure>(&meta_or_fail)) {
      if (f->cache_may_answer)
        if (auto p = cached_pointer(repo_id, path, revision)) return *p;
      if (f->kind == HubErrorKind::network)
        throw HubError(HubErrorKind::network,
                       f->message + ", and " + what + " is not in the " + cache_hint() +
                           "; check the network, or set HF_HUB_OFFLINE=1 to use only the cache");
      throw HubError(f->kind, f->message);
    }
    const FileMetadata& m = std::get<FileMetadata>(meta_or_fail);
    std::string pointer = cache_.pointer_path(repo_id, m.commit, path);
    std::error_code ec;
    if (fs::exists(pointer, ec)) {
      try {
        cache_.write_ref(repo_id, revision, m.commit);
      } catch (const HubError&) {
        // A read-only cache that already holds the file is still usable.
      }
      return pointer;
    }
    fs::create_directories(cache_.repo_dir(repo_id) + "/blobs", ec);
    if (ec)
      throw HubError(HubErrorKind::filesystem,
                     cache_.repo_dir(repo_id) + "/blobs: cannot create (" + ec.message() + ")");
    cache_.tag_cache_dir();
    cache_.write_ref(repo_id, revision, m.commit);
    FileLock lock(cache_.lock_path(repo_id, m.etag));
    std::string blob = cache_.blob_path(repo_id, m.etag);
    if (!fs::exists(blob, ec)) fetch_blob(repo_id, path, m);
    cache_.link_pointer(repo_id, m.commit, path, m.etag);
    return pointer;
  }

  // GETs the bytes into blobs/<etag>.incomplete (resuming what is there), verifies, renames into
  // blobs/<etag>.
  void fetch_blob(const std::string& repo_id, const std::string& path, const FileMetadata& m) {
    std::string incomplete = cache_.incomplete_path(repo_id, m.etag);
    std::string blob = cache_.blob_path(repo_id, m.etag);
    std::string what = "'" + path + "' of '" + repo_id + "' (commit " + m.commit + ")";
    std::error_code ec;
    uint64_t have = fs::exists(incomplete, ec) ? fs::file_size(incomplete, ec) : 0;
    if (ec) have = 0;
    if (m.size && have > *m.size) have = 0;  // longer than the file: not a prefix of it
    std::FILE* out = std::fopen(incomplete.c_str(), have > 0 ? "ab" : "wb");
    if (!out) throw HubError(HubErrorKind::filesystem, incomplete + ": cannot open for writing");
    std::unique_ptr<std::FILE, int (*)(std::FILE*)> out_guard(out, &std::fclose);

    bool show = opt_.progress == ProgressMode::always ||
                (opt_.progress == ProgressMode::automatic && stderr_is_terminal());
    ProgressBar bar(show, path, m.size, have);
    int retries_left = opt_.max_retries;
    std::string url = m.location;
    bool send_auth = is_hub_url(url, opt_.endpoint);
    int hops = 0;
    while (!(m.size && have == *m.size)) {
      HttpRequest req;
      req.url = url;
      if (send_auth) req.headers = auth_headers(url);
      if (have > 0) req.headers.push_back("Range: bytes=" + std::to_string(have) + "-");
      req.connect_timeout_s = opt_.metadata_timeout_s;
      req.stall_timeout_s = opt_.stall_timeout_s;
      bool started = false;
      bool write_failed = false;
      uint64_t got = 0;
      req.sink = [&](const HttpResponse& head, const char* data, size_t n) {
        // Bodies of redirects and errors are not file content; the status tells what happened.
        if (head.status != 200 && head.status != 206) return true;
        if (!started) {
          started = true;
          if (head.status == 200 && have > 0) {
            // The server ignored the Range: start the file over.
            std::fflush(out);
            if (::ftruncate(::fileno(out), 0) != 0) return false;
            std::fseek(out, 0, SEEK_SET);
            have = 0;
            bar.reset(0);
          }
        }
        if (std::fwrite(data, 1, n, out) != n) {
          write_failed = true;
          return false;
        }
        have += n;
        got += n;
        bar.add(n);
        return true;
      };
      HttpResult res = http_.perform(req);
      std::fflush(out);
      if (write_failed)
        throw HubError(HubErrorKind::filesystem, incomplete + ": write failed (disk full?)");
      const HttpResponse& r = res.response;
      if (res.failure == TransportFailure::none) {
        if (r.is_redirect() && ++hops < kMaxRedirects) {
          std::string target = url_join(url, *r.header("Location"));
          if (url_origin(target) != url_origin(url))
            send_auth = send_auth && is_hub_url(target, opt_.endpoint);
          url = target;
          continue;
        }
        if (r.status == 416 && have > 0) {
          // Our partial file does not fit the server's: begin again from zero.
          if (--retries_left < 0) break;
          std::fflush(out);
          if (::ftruncate(::fileno(out), 0) != 0)
            throw HubError(HubErrorKind::filesystem, incomplete + ": cannot truncate");
          std::fseek(out, 0, SEEK_SET);
          have = 0;
          continue;
        }
        if (r.status >= 300 && !is_hub_url(url, opt_.endpoint))
          throw HubError(HubErrorKind::server,
                         "download of " + what + " from " + url_origin(url) + " failed (HTTP " +
                             std::to_string(r.status) +
                             "); its signed link may have expired, run again");
        if (r.status >= 300) {
          auto f =
              http_failure(r, url, opt_.endpoint, repo_id, m.commit, path, opt_.token && send_auth);
          throw HubError(f.kind, f.message);
        }
        break;  // complete
      }
      // Broken or stalled transfer: resume from what we have; give up after max_retries without
      // progress.
      if (got > 0) retries_left = opt_.max_retries;
      if (--retries_left < 0 || res.failure == TransportFailure::aborted ||
          res.failure == TransportFailure::other)
        throw HubError(HubErrorKind::network, "download of " + what + " from " + url_origin(url) +
                                                  " failed after " + std::to_string(have) +
                                                  " bytes (" + res.error +
                                                  "); run again to resume from " + incomplete);
      if (got == 0) std::this_thread::sleep_for(std::chrono::milliseconds(500));
    }
    out_guard.reset();

    auto corrupt = [&](const std::string& why) {
      fs::remove(incomplete, ec);
      throw HubError(HubErrorKind::corrupt,
                     "download of " + what + " is corrupt: " + why +
                         "; the partial file was deleted, run again to download it anew");
    };
    if (m.size && have != *m.size)
      corrupt("got " + std::to_string(have) + " bytes, the hub announced " +
              std::to_string(*m.size));
    EtagCheck check = verify_file_against_etag(incomplete, m.etag);
    if (!check.ok)
      corrupt(check.algorithm + " is " + check.actual + ", the hub's ETag says " + m.etag);
    fs::rename(incomplete, blob, ec);
    if (ec)
      throw HubError(HubErrorKind::filesystem,
                     blob + ": cannot move the download into place (" + ec.message() + ")");
  }

  RepoInfo resolve(const std::string& repo_id, const std::string& revision) {
    validate_repo_id(repo_id);
    validate_revision(revision);
    if (opt_.offline)
      return from_cache(repo_id, revision, HubErrorKind::not_cached,
                        "HF_HUB_OFFLINE is set and " + describe_repo(repo_id, revision) +
                            " is not in the " + cache_hint());
    std::string url =
        opt_.endpoint + "/api/models/" + repo_id + "/revision/" + url_quote(revision, false);
    HttpResult res;
    for (int hop = 0;; ++hop) {
      HttpRequest req;
      req.url = url;
      req.headers = auth_headers(url);
      req.connect_timeout_s = opt_.metadata_timeout_s;
      req.timeout_s = opt_.metadata_timeout_s * 3;
      res = http_.perform(req);
      if (res.failure != TransportFailure::none) {
        auto f = transport_failure(res, url);
        return from_cache(repo_id, revision, HubErrorKind::network,
                          f.message + ", and " + describe_repo(repo_id, revision) +
                              " is not in the " + cache_hint() +
                              "; check the network, or set HF_HUB_OFFLINE=1 to use only the cache");
      }
      if (!res.response.is_redirect() || hop + 1 >= kMaxRedirects) break;
      std::string target = url_join(url, *res.response.header("Location"));
      if (!is_hub_url(target, opt_.endpoint)) break;
      url = target;
    }
    const HttpResponse& r = res.response;
    if (r.status != 200) {
      auto f = http_failure(r, url, opt_.endpoint, repo_id, revision, std::nullopt,
                            opt_.token.has_value());
      // As huggingface_hub does: a cached copy still answers when the hub refuses (token gone,
      // hub down); only a revision the hub says does not exist is final.
      if (f.cache_may_answer) return from_cache(repo_id, revision, f.kind, f.message);
      throw HubError(f.kind, f.message);
    }
    RepoInfo info;
    info.repo_id = repo_id;
    info.revision = revision;
    std::string where = url + " (repo info)";
    JsonMap j;
    try {
      j = JsonMap::parse(r.body);
    } catch (const nlohmann::json::exception& e) {
      throw HubError(HubErrorKind::server, where + ": response is not JSON (" + e.what() + ")");
    }
    try {
      info.commit = json_get<std::string>(j, "sha", where);
      if (!is_sha1_hex(info.commit))
        throw HubError(HubErrorKind::server, where + ": 'sha' is not a commit hash");
      if (auto g = j.find("gated"); g != j.end())
        info.gated = g->is_string() || (g->is_boolean() && g->get<bool>());
      if (auto s = j.find("siblings"); s != j.end() && s->is_array()) {
        for (const auto& e : *s) {
          RepoFile f;
          f.path = json_get<std::string>(e, "rfilename", where + ": siblings[]");
          if (auto sz = e.find("size"); sz != e.end() && sz->is_number_unsigned())
            f.size = sz->get<uint64_t>();
          info.files.push_back(std::move(f));
        }
      }
    } catch (const HubError&) {
      throw;
    } catch (const Error& e) {
      throw HubError(HubErrorKind::server, e.what());
    }
    return info;
  }

  RepoInfo from_cache(const std::string& repo_id, const std::string& revision, HubErrorKind kind,
                      const std::string& message) const {
    auto commit = cache_.resolve_commit(repo_id, revision);
    std::error_code ec;
    if (!commit || !fs::is_directory(cache_.snapshot_dir(repo_id, *commit), ec))
      throw HubError(kind, message);
    RepoInfo info;
    info.repo_id = repo_id;
    info.revision = revision;
    info.commit = *commit;
    info.from_cache = true;
    for (auto& p : cache_.snapshot_files(repo_id, *commit)) info.files.push_back({p, std::nullopt});
    return info;
  }

  std::string snapshot_download(const std::string& repo_id, const std::string& revision,
                                const std::vector<std::string>& allow_patterns) {
    RepoInfo info = resolve(repo_id, revision);
    std::string dir = cache_.snapshot_dir(repo_id, info.commit);
    if (info.from_cache) {
      // Without the hub's file list we cannot tell a complete snapshot from a partial one; insist
      // on at least one file matching what was asked for.
      bool any = std::any_of(info.files.begin(), info.files.end(), [&](const RepoFile& f) {
        return path_matches_any(f.path, allow_patterns);
      });
      if (!any)
        throw HubError(
            opt_.offline ? HubErrorKind::not_cached : HubErrorKind::network,
            "the cached snapshot " + dir + " of " + describe_repo(repo_id, revision) +
                " holds no file matching the requested patterns" +
                (opt_.offline ? " and HF_HUB_OFFLINE is set" : " and the hub is unreachable"));
      return dir;
    }
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec)
      throw HubError(HubErrorKind::filesystem, dir + ": cannot create (" + ec.message() + ")");
    cache_.write_ref(repo_id, revision, info.commit);
    for (const auto& f : info.files)
      if (path_matches_any(f.path, allow_patterns)) download_file(repo_id, f.path, info.commit);
    return dir;
  }

 private:
  const HubOptions& opt_;
  const HubCache& cache_;
  HttpClient& http_;
};

}  // namespace

std::optional<std::string> HubClient::cached_snapshot(const std::string& repo_id,
                                                      const std::string& revision) const {
  validate_repo_id(repo_id);
  validate_revision(revision);
  auto commit = cache_.resolve_commit(repo_id, revision);
  if (!commit) return std::nullopt;
  std::string dir = cache_.snapshot_dir(repo_id, *commit);
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return std::nullopt;
  return dir;
}

RepoInfo HubClient::resolve(const std::string& repo_id, const std::string& revision) {
  return Session(options_, cache_, net_->http).resolve(repo_id, revision);
}

std::string HubClient::download_file(const std::string& repo_id, const std::string& path,
                                     const std::string& revision) {
  return Session(options_, cache_, net_->http).download_file(repo_id, path, revision);
}

std::string HubClient::snapshot_download(const std::string& repo_id, const std::string& revision,
                                         const std::vector<std::string>& allow_patterns) {
  return Session(options_, cache_, net_->http).snapshot_download(repo_id, revision, allow_patterns);
}

}  // namespace tether::hub
