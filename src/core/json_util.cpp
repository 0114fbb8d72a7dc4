// JSON config reading with errors that name the file and field at fault (see json_util.h).
#include "core/json_util.h"

#include <fstream>

namespace tether {

template <typename J>
J read_json_file(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw Error(ErrorCode::not_found, path + ": cannot open");
  std::stringstream ss;
  ss << in.rdbuf();
  J j = J::parse(ss.str(), nullptr, /*allow_exceptions=*/false);
  if (j.is_discarded()) throw Error(ErrorCode::format, path + ": not valid JSON");
  return j;
}

template Json read_json_file<Json>(const std::string&);
template JsonMap read_json_file<JsonMap>(const std::string&);

}  // namespace tether
