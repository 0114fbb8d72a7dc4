// ETag checks of downloaded files (see hash.h).
#include "hub/hash.h"

namespace tether::hub {

EtagCheck verify_file_against_etag(const std::string& path, const std::string& etag) {
  EtagCheck r;
  if (is_sha256_hex(etag)) {
    r.checked = true;
    r.algorithm = "sha256";
    r.actual = sha256_file_hex(path);
  } else if (is_sha1_hex(etag)) {
    r.checked = true;
    r.algorithm = "git-sha1";
    r.actual = git_blob_sha1_file_hex(path);
  } else {
    return r;
  }
  r.ok = r.actual == etag;
  return r;
}

}  // namespace tether::hub
