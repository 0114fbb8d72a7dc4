// Checking downloads against the hub's ETags (the digests themselves live in core/hash.h).
#pragma once

#include <string>

#include "core/hash.h"

namespace tether::hub {

using ::tether::git_blob_sha1_file_hex;
using ::tether::git_blob_sha1_hex;
using ::tether::is_sha1_hex;
using ::tether::is_sha256_hex;
using ::tether::sha256_file_hex;
using ::tether::sha256_hex;

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
