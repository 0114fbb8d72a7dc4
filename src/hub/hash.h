// File digests used to check downloads against the hub's ETags: sha256 (LFS files) and git blob
// sha1.
#pragma once

#include <cstdint>
#include <string>

namespace tether::hub {

// Lower-case hex digests of a whole file; throw HubError(filesystem) if it cannot be read.
std::string sha256_file_hex(const std::string& path);
// sha1 of "blob <size>\0<content>": the id git gives the file's content, which the hub sends as the
// ETag of files stored in git rather than LFS.
std::string git_blob_sha1_file_hex(const std::string& path);

std::string sha256_hex(const std::string& data);
std::string git_blob_sha1_hex(const std::string& data);

bool is_sha256_hex(const std::string& s);  // 64 lower-case hex digits
bool is_sha1_hex(const std::string& s);    // 40 lower-case hex digits (also a commit hash)

// Checks a downloaded blob against its normalised ETag: a 64-hex ETag is the sha256 of an LFS file,
// a 40-hex one the git blob id. Any other form (e.g. a xet hash) cannot be checked here; then only
// the size is.
struct EtagCheck {
  bool checked = false;   // the ETag had a verifiable form
  bool ok = true;         // digest matched (or nothing to check)
  std::string algorithm;  // "sha256" or "git-sha1"
  std::string actual;     // digest of the file
};
EtagCheck verify_file_against_etag(const std::string& path, const std::string& etag);

}  // namespace tether::hub
