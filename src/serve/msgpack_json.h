// JSON values (the pipeline's answers) as MessagePack, for the ZMQ transports' replies.
#pragma once

#include "core/json_util.h"
#include "serve/msgpack.h"

namespace tether::serve::msgpack {

// Writes `j`: objects as maps (keys in order), numbers as integers or float64, strings as str.
void write_json(Writer& w, const Json& j);

}  // namespace tether::serve::msgpack
