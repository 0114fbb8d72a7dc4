// The wedge metric tables and the three ways they are fed: registration, per-request reports, events and gauges.
#include "serve/wedge_metrics.h"

namespace tether::serve {

namespace {

using runtime::WedgeReport;
using runtime::Wedges;
using Out = std::vector<WedgeSample>;

void once_if(bool happened, Out& out) {
  if (happened) out.push_back({"", 1});
}

constexpr const char* kFallbackHelp = "Requests forwarded to the cloud fallback, by outcome.";

bool has_fallback(const Wedges& w) { return !w.options().cloud_fallback.empty(); }

std::string join_labels(const std::string& host, const std::string& own) {
  if (host.empty()) return own;
  if (own.empty()) return host;
  return host + "," + own;
}

}  // namespace

const std::vector<WedgeCounter>& wedge_counters() {
  static const std::vector<WedgeCounter> table = {
      {"tether_guard_clamped_total", "Responses the action guard changed.", "",
       [](const Wedges& w) { return w.guard_enabled(); },
       [](const WedgeReport& r, Out& out) { once_if(r.guard.clamped, out); }, std::nullopt},
      {"tether_guard_violations_total", "Values the action guard clamped, by joint and limit.", "", nullptr,
       [](const WedgeReport& r, Out& out) {
         for (const auto& v : r.guard.violations)
           out.push_back({"joint=\"" + escape_label(v.joint) + "\",limit=\"" + escape_label(v.limit) + "\"", 1});
       },
       std::nullopt},
      {"tether_action_skip_total", "Requests answered from the cached chunk (similarity).", "",
       [](const Wedges& w) { return w.skip_enabled(); },
       [](const WedgeReport& r, Out& out) { once_if(r.skipped, out); }, std::nullopt},
      {"tether_last_good_chunk_total", "Deadline misses answered with the last good chunk.", "", nullptr,
       [](const WedgeReport& r, Out& out) { once_if(r.source == runtime::ActionSource::last_good, out); },
       std::nullopt},
      {"tether_denoise_steps_total", "Denoise steps run (adaptive steps).", "",
       [](const Wedges& w) { return w.options().sampler.adaptive_threshold > 0; },
       [](const WedgeReport& r, Out& out) {
         if (r.denoise_steps_used > 0) out.push_back({"", double(r.denoise_steps_used)});
       },
       std::nullopt},
      {"tether_denoise_runs_total", "Forward passes counted in tether_denoise_steps_total.", "", nullptr,
       [](const WedgeReport& r, Out& out) { once_if(r.denoise_steps_used > 0, out); }, std::nullopt},
      {"tether_rtc_total", "Requests denoised with real-time chunking guidance.", "",
       [](const Wedges& w) { return w.options().sampler.rtc; },
       [](const WedgeReport& r, Out& out) { once_if(r.rtc_applied, out); }, std::nullopt},
      {"tether_deadline_exceeded_total", "Requests that missed --deadline-ms.", "",
       [](const Wedges& w) { return w.options().deadline_ms > 0; }, nullptr, WedgeEvent::deadline_exceeded},
      {"tether_fallback_total", kFallbackHelp, "outcome=\"success\"", has_fallback, nullptr,
       WedgeEvent::fallback_success},
      {"tether_fallback_total", kFallbackHelp, "outcome=\"failure\"", has_fallback, nullptr,
       WedgeEvent::fallback_failure},
      {"tether_circuit_rejected_total", "Requests refused while the circuit was open.", "",
       [](const Wedges& w) { return w.breaker().enabled(); }, nullptr, WedgeEvent::circuit_rejected},
      {"tether_trace_write_errors_total", "Trace lines that could not be written.", "", nullptr, nullptr,
       WedgeEvent::trace_write_error},
  };
  return table;
}

const std::vector<WedgeGauge>& wedge_gauges() {
  using Value = std::optional<double>;
  static const std::vector<WedgeGauge> table = {
      {"tether_circuit_open", "1 while the circuit breaker refuses local inference (open or half-open).",
       [](Wedges& w) -> Value {
         if (!w.breaker().enabled()) return std::nullopt;
         return w.breaker().state() == runtime::CircuitBreaker::State::closed ? 0 : 1;
       }},
      {"tether_circuit_opened_total", "Times the circuit breaker opened.",
       [](Wedges& w) -> Value {
         if (!w.breaker().enabled()) return std::nullopt;
         return double(w.breaker().times_opened());
       }},
      {"tether_consecutive_failures", "Consecutive failed inferences.",
       [](Wedges& w) -> Value {
         if (!w.breaker().enabled()) return std::nullopt;
         return double(w.breaker().consecutive_failures());
       }},
      {"tether_injected_latency_ms", "Synthetic delay added to every forward pass.",
       [](Wedges& w) -> Value {
         if (w.options().inject_latency_ms <= 0) return std::nullopt;
         return w.options().inject_latency_ms;
       }},
      {"tether_episodes", "Episodes the server holds state for.",
       [](Wedges& w) -> Value { return double(w.episodes().size()); }},
      {"tether_trace_lines_total", "Trace lines written since start.",
       [](Wedges& w) -> Value {
         if (!w.recorder()) return std::nullopt;
         return double(w.recorder()->lines_written());
       }},
      {"tether_trace_write_errors", "Trace lines lost to I/O errors since start.",
       [](Wedges& w) -> Value {
         if (!w.recorder()) return std::nullopt;
         return double(w.recorder()->write_errors());
       }},
  };
  return table;
}

void register_wedge_metrics(Metrics& metrics, const Wedges& wedges, const std::string& host_labels) {
  for (const auto& c : wedge_counters())
    if (c.shown_at_zero && c.shown_at_zero(wedges))
      metrics.add_counter(c.name, c.help, 0, join_labels(host_labels, c.labels));
}

void count_wedge_report(Metrics& metrics, const WedgeReport& report, const std::string& host_labels) {
  Out samples;
  for (const auto& c : wedge_counters()) {
    if (!c.from_report) continue;
    samples.clear();
    c.from_report(report, samples);
    for (const auto& s : samples) metrics.add_counter(c.name, c.help, s.value, join_labels(host_labels, s.labels));
  }
}

void count_wedge_event(Metrics& metrics, WedgeEvent event, const std::string& host_labels) {
  for (const auto& c : wedge_counters())
    if (c.event == event) metrics.add_counter(c.name, c.help, 1, join_labels(host_labels, c.labels));
}

void refresh_wedge_gauges(Metrics& metrics, Wedges& wedges, const std::string& host_labels) {
  for (const auto& g : wedge_gauges())
    if (const auto v = g.read(wedges)) metrics.set_gauge(g.name, g.help, *v, host_labels);
}

}  // namespace tether::serve
