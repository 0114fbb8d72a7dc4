// The on-disk cache, laid out exactly as huggingface_hub lays it out so Python tools and Tether
// share files:
//   <root>/models--{org}--{name}/blobs/<etag>                 file contents, named by ETag (sha256
//   or git sha1) <root>/models--{org}--{name}/snapshots/<commit>/<path>    relative symlink to
//   ../../blobs/<etag> <root>/models--{org}--{name}/refs/<revision>              commit hash, no
//   trailing newline
#pragma once

#include <optional>
#include <string>
#include <vector>

namespace tether::hub {

// tether::hf_hub_cache() and tether::hf_home() (core/hf_paths.h), where the precedence is defined once.
std::string default_cache_root();
std::string default_hf_home();

// Throw HubError(invalid) for ids and paths huggingface_hub would also refuse, or that would escape
// the cache.
void validate_repo_id(const std::string& repo_id);
void validate_revision(const std::string& revision);
void validate_repo_path(const std::string& path);

// "models--org--name".
std::string repo_folder_name(const std::string& repo_id);

class HubCache {
 public:
  explicit HubCache(std::string root) : root_(std::move(root)) {}
  const std::string& root() const { return root_; }

  std::string repo_dir(const std::string& repo_id) const;
  std::string blob_path(const std::string& repo_id, const std::string& etag) const;
  std::string incomplete_path(const std::string& repo_id, const std::string& etag) const;
  std::string snapshot_dir(const std::string& repo_id, const std::string& commit) const;
  std::string pointer_path(const std::string& repo_id, const std::string& commit,
                           const std::string& path) const;
  std::string lock_path(const std::string& repo_id, const std::string& etag) const;

  // A 40-hex revision is its own commit; otherwise refs/<revision>. nullopt when nothing is
  // recorded.
  std::optional<std::string> resolve_commit(const std::string& repo_id,
                                            const std::string& revision) const;
  // Records refs/<revision> = commit (atomically), unless the revision is the commit itself.
  void write_ref(const std::string& repo_id, const std::string& revision,
                 const std::string& commit) const;
  // snapshots/<commit>/<path> -> relative path to blobs/<etag>, replacing whatever was there.
  void link_pointer(const std::string& repo_id, const std::string& commit, const std::string& path,
                    const std::string& etag) const;
  // Files under snapshots/<commit>, as repo paths with '/' separators, sorted.
  std::vector<std::string> snapshot_files(const std::string& repo_id,
                                          const std::string& commit) const;
  // Writes the CACHEDIR.TAG backup tools look for, once.
  void tag_cache_dir() const;

 private:
  std::string root_;
};

// Exclusive advisory lock (flock) on a file, created if needed: the same lock huggingface_hub takes
// under <root>/.locks, so a Python download and ours do not write the same blob at once.
class FileLock {
 public:
  explicit FileLock(const std::string& path);
  ~FileLock();
  FileLock(const FileLock&) = delete;
  FileLock& operator=(const FileLock&) = delete;

 private:
  int fd_ = -1;
};

}  // namespace tether::hub
