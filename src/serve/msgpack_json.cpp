// JSON to MessagePack, and parsing a msgpack request map.
#include "serve/msgpack_json.h"

#include "serve/http_error.h"

namespace tether::serve::msgpack {

void write_json(Writer& w, const Json& j) {
  switch (j.type()) {
    case Json::value_t::null: w.nil(); break;
    case Json::value_t::boolean: w.boolean(j.get<bool>()); break;
    case Json::value_t::number_integer: w.integer(j.get<int64_t>()); break;
    case Json::value_t::number_unsigned: w.uinteger(j.get<uint64_t>()); break;
    case Json::value_t::number_float: w.float64(j.get<double>()); break;
    case Json::value_t::string: w.str(j.get_ref<const std::string&>()); break;
    case Json::value_t::array:
      w.array(uint32_t(j.size()));
      for (const auto& v : j) write_json(w, v);
      break;
    case Json::value_t::object:
      w.map(uint32_t(j.size()));
      for (auto it = j.begin(); it != j.end(); ++it) {
        w.str(it.key());
        write_json(w, it.value());
      }
      break;
    case Json::value_t::binary: w.bin(std::string_view(reinterpret_cast<const char*>(j.get_binary().data()), j.get_binary().size())); break;
    case Json::value_t::discarded: w.nil(); break;
  }
}

Value parse_map(std::string_view bytes, const char* what, const char* expected) {
  Value root;
  try {
    root = parse(bytes);
  } catch (const Error& e) {
    throw HttpError(400, "bad_msgpack", std::string("the ") + what + " is not valid msgpack: " + e.what());
  }
  if (!root.is_map())
    throw HttpError(400, "bad_msgpack",
                    std::string("the ") + what + " must be a msgpack map " + expected + ", got " + kind_name(root.kind));
  return root;
}

}  // namespace tether::serve::msgpack
