// Hugging Face Hub client: resolves revisions, downloads files and snapshots into the
// huggingface_hub cache layout (shared with Python tools), resumes partial downloads and verifies
// them against their ETags.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "hub/cache.h"
#include "hub/hub_error.h"

namespace tether::hub {

struct RepoFile {
  std::string path;              // '/'-separated path inside the repo
  std::optional<uint64_t> size;  // when the listing carries it
};

struct RepoInfo {
  std::string repo_id;
  std::string revision;  // as asked for ("main", a tag, or a commit)
  std::string commit;    // the 40-hex commit it resolved to
  std::vector<RepoFile> files;
  bool gated = false;       // the hub marks the repo gated (downloads need an accepted license)
  bool from_cache = false;  // answered from refs/ and snapshots/ without the network
};

enum class ProgressMode { automatic, always, never };  // automatic: only when stderr is a terminal

struct HubOptions {
  std::string endpoint = "https://huggingface.co";  // no trailing '/'
  std::string cache_root;                           // empty: default_cache_root()
  std::optional<std::string> token;  // sent as "Authorization: Bearer" to the hub only
  bool offline = false;              // never touch the network; answer from the cache
  ProgressMode progress = ProgressMode::automatic;
  long metadata_timeout_s = 10;  // HEAD and API calls (HF_HUB_ETAG_TIMEOUT)
  long stall_timeout_s =
      10;  // a download with no data for this long is retried (HF_HUB_DOWNLOAD_TIMEOUT)
  int max_retries = 5;  // re-tries of a broken transfer with no progress in between
};

// HF_TOKEN, else HUGGING_FACE_HUB_TOKEN, else the file at HF_TOKEN_PATH or $HF_HOME/token; blank =
// none.
std::optional<std::string> token_from_env();
// HF_HUB_OFFLINE / TRANSFORMERS_OFFLINE set to 1, ON, YES or TRUE.
bool offline_from_env();

// fnmatch-style (case-sensitive; '*' also crosses '/'), as huggingface_hub filters snapshot files;
// a pattern ending in '/' matches everything below that folder.
bool path_matches(const std::string& path, const std::string& pattern);
bool path_matches_any(const std::string& path,
                      const std::vector<std::string>& patterns);  // empty: all

// Not thread-safe: one client per thread (it keeps one connection alive across a snapshot's files).
class HubClient {
 public:
  explicit HubClient(HubOptions options);
  ~HubClient();
  HubClient(HubClient&&) noexcept;
  HubClient& operator=(HubClient&&) noexcept;

  // Options from HF_ENDPOINT, HF_HUB_CACHE/HF_HOME, HF_TOKEN (or the token file), HF_HUB_OFFLINE,
  // HF_HUB_ETAG_TIMEOUT and HF_HUB_DOWNLOAD_TIMEOUT.
  static HubClient from_env();

  // The commit a revision points at and the files it holds (API call; offline or unreachable: the
  // cache).
  RepoInfo resolve(const std::string& repo_id, const std::string& revision = "main");
  // One file into the cache; returns its snapshots/<commit>/<path> path.
  std::string download_file(const std::string& repo_id, const std::string& path,
                            const std::string& revision = "main");
  // Every file matching allow_patterns (all when empty); returns the snapshots/<commit> folder.
  std::string snapshot_download(const std::string& repo_id, const std::string& revision = "main",
                                const std::vector<std::string>& allow_patterns = {});
  // The cached snapshots/<commit> folder for a revision, without any network access.
  std::optional<std::string> cached_snapshot(const std::string& repo_id,
                                             const std::string& revision = "main") const;

  const HubOptions& options() const { return options_; }
  const HubCache& cache() const { return cache_; }

 private:
  struct Net;
  HubOptions options_;
  HubCache cache_;
  std::unique_ptr<Net> net_;
};

}  // namespace tether::hub
