// The huggingface_hub-compatible cache: paths, refs, relative snapshot symlinks and the blob lock.
#include "hub/cache.h"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <filesystem>
#include <fstream>
#include <random>

#include "core/hf_paths.h"
#include "hub/hash.h"
#include "hub/hub_error.h"

namespace fs = std::filesystem;

namespace tether::hub {
namespace {

bool has_bad_component(const std::string& path) {
  std::stringstream ss(path);
  std::string part;
  while (std::getline(ss, part, '/'))
    if (part.empty() || part == "." || part == "..") return true;
  return path.back() == '/';
}

void fs_fail(const std::string& what, const std::string& path, const std::error_code& ec) {
  throw HubError(HubErrorKind::filesystem, path + ": cannot " + what + " (" + ec.message() + ")");
}

}  // namespace

std::string default_hf_home() { return hf_home(); }

std::string default_cache_root() { return hf_hub_cache(); }

void validate_repo_id(const std::string& repo_id) {
  auto fail = [&](const std::string& why) {
    throw HubError(HubErrorKind::invalid,
                   "repo id '" + repo_id + "': " + why + " (expected 'org/name')");
  };
  if (repo_id.empty()) fail("empty");
  size_t slash = repo_id.find('/');
  if (slash != std::string::npos && repo_id.find('/', slash + 1) != std::string::npos)
    fail("more than one '/'");
  if (repo_id.find("--") != std::string::npos || repo_id.find("..") != std::string::npos)
    fail("'--' and '..' are not allowed");
  auto check_part = [&](const std::string& part) {
    if (part.empty() || part.size() > 96) fail("each part must have 1 to 96 characters");
    for (char c : part)
      if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '-' || c == '_' || c == '.'))
        fail(std::string("character '") + c + "' is not allowed");
    auto edge_ok = [](char c) { return std::isalnum(static_cast<unsigned char>(c)) || c == '_'; };
    if (!edge_ok(part.front()) || !edge_ok(part.back()))
      fail("parts must start and end with a letter or digit");
  };
  if (slash == std::string::npos) {
    check_part(repo_id);
  } else {
    check_part(repo_id.substr(0, slash));
    check_part(repo_id.substr(slash + 1));
  }
  if (repo_id.size() >= 4 && repo_id.compare(repo_id.size() - 4, 4, ".git") == 0)
    fail("must not end in '.git'");
}

void validate_revision(const std::string& revision) {
  if (revision.empty() || revision[0] == '/' || has_bad_component(revision))
    throw HubError(HubErrorKind::invalid,
                   "revision '" + revision + "' is not a valid branch, tag or commit");
}

void validate_repo_path(const std::string& path) {
  if (path.empty() || path[0] == '/' || path.find('\\') != std::string::npos ||
      has_bad_component(path))
    throw HubError(HubErrorKind::invalid,
                   "file path '" + path + "' is not a relative path inside the repo");
}

std::string repo_folder_name(const std::string& repo_id) {
  std::string out = "models";
  std::stringstream ss(repo_id);
  std::string part;
  while (std::getline(ss, part, '/')) out += "--" + part;
  return out;
}

std::string HubCache::repo_dir(const std::string& repo_id) const {
  return root_ + "/" + repo_folder_name(repo_id);
}

std::string HubCache::blob_path(const std::string& repo_id, const std::string& etag) const {
  return repo_dir(repo_id) + "/blobs/" + etag;
}

std::string HubCache::incomplete_path(const std::string& repo_id, const std::string& etag) const {
  return blob_path(repo_id, etag) + ".incomplete";
}

std::string HubCache::snapshot_dir(const std::string& repo_id, const std::string& commit) const {
  return repo_dir(repo_id) + "/snapshots/" + commit;
}

std::string HubCache::pointer_path(const std::string& repo_id, const std::string& commit,
                                   const std::string& path) const {
  return snapshot_dir(repo_id, commit) + "/" + path;
}

std::string HubCache::lock_path(const std::string& repo_id, const std::string& etag) const {
  return root_ + "/.locks/" + repo_folder_name(repo_id) + "/" + etag + ".lock";
}

std::optional<std::string> HubCache::resolve_commit(const std::string& repo_id,
                                                    const std::string& revision) const {
  if (is_sha1_hex(revision)) return revision;
  std::ifstream in(repo_dir(repo_id) + "/refs/" + revision, std::ios::binary);
  if (!in) return std::nullopt;
  std::string commit((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  // huggingface_hub writes the hash bare; tolerate a trailing newline from hand-made caches.
  while (!commit.empty() &&
         (commit.back() == '\n' || commit.back() == '\r' || commit.back() == ' '))
    commit.pop_back();
  if (!is_sha1_hex(commit)) return std::nullopt;
  return commit;
}

void HubCache::write_ref(const std::string& repo_id, const std::string& revision,
                         const std::string& commit) const {
  if (revision == commit) return;
  fs::path ref = repo_dir(repo_id) + "/refs/" + revision;
  if (resolve_commit(repo_id, revision) == commit)
    return;  // a read-only cache that is already right stays untouched
  std::error_code ec;
  fs::create_directories(ref.parent_path(), ec);
  if (ec) fs_fail("create directory", ref.parent_path().string(), ec);
  std::random_device rd;
  fs::path tmp = ref;
  tmp += ".";
  tmp += std::to_string(rd());
  tmp += ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out << commit;
    if (!out.flush()) throw HubError(HubErrorKind::filesystem, tmp.string() + ": cannot write ref");
  }
  fs::rename(tmp, ref, ec);
  if (ec) {
    fs::remove(tmp);
    fs_fail("rename into place", ref.string(), ec);
  }
}

void HubCache::link_pointer(const std::string& repo_id, const std::string& commit,
                            const std::string& path, const std::string& etag) const {
  fs::path pointer = pointer_path(repo_id, commit, path);
  std::error_code ec;
  fs::create_directories(pointer.parent_path(), ec);
  if (ec) fs_fail("create directory", pointer.parent_path().string(), ec);
  // From snapshots/<commit>/<dirs...>/ back up to the repo folder: two levels plus one per
  // directory in `path`.
  size_t ups = 2 + static_cast<size_t>(std::count(path.begin(), path.end(), '/'));
  std::string target;
  for (size_t i = 0; i < ups; ++i) target += "../";
  target += "blobs/" + etag;
  fs::remove(pointer, ec);
  fs::create_symlink(target, pointer, ec);
  if (ec) {
    // Another process linked it between remove and create: fine when it points at the same blob.
    std::error_code ec2;
    if (fs::is_symlink(pointer, ec2) && fs::read_symlink(pointer, ec2) == fs::path(target)) return;
    fs_fail("create symlink", pointer.string(), ec);
  }
}

std::vector<std::string> HubCache::snapshot_files(const std::string& repo_id,
                                                  const std::string& commit) const {
  std::vector<std::string> out;
  fs::path dir = snapshot_dir(repo_id, commit);
  std::error_code ec;
  if (!fs::is_directory(dir, ec)) return out;
  for (auto it = fs::recursive_directory_iterator(dir, ec);
       !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
    // A dangling pointer (blob deleted by a cache cleaner) is not a cached file.
    if (fs::is_regular_file(it->path(), ec))
      out.push_back(it->path().lexically_relative(dir).generic_string());
  }
  std::sort(out.begin(), out.end());
  return out;
}

void HubCache::tag_cache_dir() const {
  fs::path tag = fs::path(root_) / "CACHEDIR.TAG";
  std::error_code ec;
  if (fs::exists(tag, ec)) return;
  std::ofstream out(tag, std::ios::binary);
  // The signature line is fixed by the Cache Directory Tagging Specification.
  out << "Signature: 8a477f597d28d172789f06886806bc55\n"
         "# This is the Hugging Face model cache, shared with huggingface_hub.\n";
}

FileLock::FileLock(const std::string& path) {
  std::error_code ec;
  fs::create_directories(fs::path(path).parent_path(), ec);
  if (ec) fs_fail("create directory", fs::path(path).parent_path().string(), ec);
  fd_ = ::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd_ < 0) throw HubError(HubErrorKind::filesystem, path + ": cannot open lock file");
  while (::flock(fd_, LOCK_EX) != 0) {
    if (errno != EINTR) {
      ::close(fd_);
      throw HubError(HubErrorKind::filesystem, path + ": cannot lock");
    }
  }
}

FileLock::~FileLock() {
  if (fd_ >= 0) {
    ::flock(fd_, LOCK_UN);
    ::close(fd_);
  }
}

}  // namespace tether::hub
