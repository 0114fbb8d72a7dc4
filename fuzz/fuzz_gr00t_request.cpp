// libFuzzer target: any byte string as a GR00T ZMQ request yields an endpoint call (and, for get_action, ActRequests
// for its batch items, decoded for a one-group and a two-group state) or an HttpError(400) with a known code, nothing
// else.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "fuzz_spec.h"
#include "serve/gr00t_protocol.h"

namespace {

using namespace tether;

// The fake spec with its state and action split into groups, as a GR00T checkpoint's are.
const models::ModelSpec& grouped_spec() {
  static const models::ModelSpec s = [] {
    models::ModelSpec m = fuzz::fake_spec();
    m.state_groups = {{"arm", 2}, {"gripper", 1}};
    m.action_groups = {{"arm", 2}, {"gripper", 1}};
    return m;
  }();
  return s;
}

void decode_items(const serve::gr00t::Call& call, const models::ModelSpec& spec) {
  try {
    const serve::gr00t::Layout layout = serve::gr00t::observation_layout(call);
    if (layout.batch < 1) __builtin_trap();
    for (int64_t i = 0; i < std::min<int64_t>(layout.batch, 4); ++i)
      fuzz::check_accepted(serve::gr00t::decode_item(call, i, spec));
  } catch (const serve::HttpError& e) {
    fuzz::check_refusal(e, {"invalid_field", "invalid_state", "unknown_camera", "unknown_field", "missing_field"});
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  serve::gr00t::Call call;
  try {
    call = serve::gr00t::parse_call(std::string_view(reinterpret_cast<const char*>(data), size));
    if (call.endpoint == serve::gr00t::Endpoint::reset) (void)serve::gr00t::reset_episodes(call);
  } catch (const serve::HttpError& e) {
    fuzz::check_refusal(e, {"bad_msgpack", "invalid_field", "unknown_endpoint"});
    return 0;
  }
  if (call.endpoint != serve::gr00t::Endpoint::get_action) return 0;
  // One state group, and the same state split in two.
  decode_items(call, fuzz::fake_spec());
  decode_items(call, grouped_spec());
  return 0;
}
