// JSON values (the pipeline's answers) as MessagePack, for the ZMQ transports' replies; and the first step of reading a
// msgpack request, shared by Tether ZMQ, GR00T ZMQ and /act's msgpack bodies.
#pragma once

#include "core/json_util.h"
#include "serve/msgpack.h"

namespace tether::serve::msgpack {

// Writes `j`: objects as maps (keys in order), numbers as integers or float64, strings as str.
void write_json(Writer& w, const Json& j);

// `bytes` as a msgpack map, or an HttpError 400 `bad_msgpack`: "the <what> is not valid msgpack: ..." or "the <what>
// must be a msgpack map <expected>, got <kind>".
Value parse_map(std::string_view bytes, const char* what, const char* expected);

}  // namespace tether::serve::msgpack
