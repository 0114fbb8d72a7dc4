// Errors from the hub layer: a tether::Error whose kind says which of the hub's failure modes
// happened.
#pragma once

#include <string>

#include "core/error.h"

namespace tether::hub {

enum class HubErrorKind {
  gated,           // 401/403: gated or private repo, token missing, wrong, or license not accepted
  repo_not_found,  // 404 RepoNotFound
  revision_not_found,  // 404 RevisionNotFound
  entry_not_found,     // 404 for a file in an existing repo
  corrupt,             // downloaded bytes do not match the ETag hash or the announced size
  network,             // could not connect / transfer broke beyond retries
  not_cached,          // offline (HF_HUB_OFFLINE=1) and the cache does not hold what was asked for
  server,              // any other HTTP failure, or a response that is not what a hub sends
  invalid,             // malformed repo id, revision or file name
  filesystem,          // the cache directory could not be written or read
};

// Stable lower-case name of a kind ("gated", "entry_not_found", ...), for CLI output and JSON
// errors.
const char* hub_error_kind_name(HubErrorKind kind);

// The tether::ErrorCode each kind is reported under.
ErrorCode hub_error_code(HubErrorKind kind);

class HubError : public Error {
 public:
  HubError(HubErrorKind kind, const std::string& message)
      : Error(hub_error_code(kind), message), kind_(kind) {}
  HubErrorKind kind() const { return kind_; }

 private:
  HubErrorKind kind_;
};

}  // namespace tether::hub
