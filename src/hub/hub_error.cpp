// Names and tether::ErrorCode mapping of the hub error kinds.
#include "hub/hub_error.h"

namespace tether::hub {

const char* hub_error_kind_name(HubErrorKind kind) {
  switch (kind) {
    case HubErrorKind::gated:
      return "gated";
    case HubErrorKind::repo_not_found:
      return "repo_not_found";
    case HubErrorKind::revision_not_found:
      return "revision_not_found";
    case HubErrorKind::entry_not_found:
      return "entry_not_found";
    case HubErrorKind::corrupt:
      return "corrupt";
    case HubErrorKind::network:
      return "network";
    case HubErrorKind::not_cached:
      return "not_cached";
    case HubErrorKind::server:
      return "server";
    case HubErrorKind::invalid:
      return "invalid";
    case HubErrorKind::filesystem:
      return "filesystem";
  }
  return "unknown";
}

ErrorCode hub_error_code(HubErrorKind kind) {
  switch (kind) {
    case HubErrorKind::repo_not_found:
    case HubErrorKind::revision_not_found:
    case HubErrorKind::entry_not_found:
    case HubErrorKind::not_cached:
      return ErrorCode::not_found;
    case HubErrorKind::corrupt:
    case HubErrorKind::server:
      return ErrorCode::format;
    case HubErrorKind::invalid:
      return ErrorCode::invalid_argument;
    case HubErrorKind::gated:
    case HubErrorKind::network:
    case HubErrorKind::filesystem:
      return ErrorCode::io;
  }
  return ErrorCode::internal;
}

}  // namespace tether::hub
