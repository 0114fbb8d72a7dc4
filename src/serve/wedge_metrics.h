// The metrics of the safety wedges and the trace recorder, each declared once in a table: its name, its help text,
// when it is listed at zero, and what it counts (a field of the request's WedgeReport, an event, or a gauge read at
// scrape time).
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "runtime/wedges.h"
#include "serve/metrics.h"

namespace tether::serve {

// Counters bumped where something happens rather than read from a finished request's report (a request that ends
// in an error still counts its deadline miss, its refusal or its fallback attempt).
enum class WedgeEvent { deadline_exceeded, fallback_success, fallback_failure, circuit_rejected, trace_write_error };

// One labelled increment a report contributes.
struct WedgeSample {
  std::string labels;  // without braces, e.g. joint="j1",limit="velocity"; empty: none
  double value = 1;
};

struct WedgeCounter {
  const char* name;
  const char* help;
  const char* labels;  // the fixed label list of an event counter ("" for none)
  // Listed at zero from the start when this returns true for the wedges being served; null: appears with its
  // first count.
  bool (*shown_at_zero)(const runtime::Wedges&);
  // What one answered request adds (appended to `out`; nothing: no change); null for event counters.
  void (*from_report)(const runtime::WedgeReport&, std::vector<WedgeSample>& out);
  std::optional<WedgeEvent> event;  // set for event counters
};

struct WedgeGauge {
  const char* name;
  const char* help;
  // The value now, or nothing when the gauge does not apply to these wedges.
  std::optional<double> (*read)(runtime::Wedges&);
};

const std::vector<WedgeCounter>& wedge_counters();
const std::vector<WedgeGauge>& wedge_gauges();

// `host_labels` (without braces) goes in front of every series' own labels: `embodiment="TAG"` when a server serves
// several embodiments, each with its own wedges; empty for a single one.
// Once the model is bound: every counter shown at zero for these wedges.
void register_wedge_metrics(Metrics& metrics, const runtime::Wedges& wedges, const std::string& host_labels = "");
// After a request's actions are final: every counter its report feeds.
void count_wedge_report(Metrics& metrics, const runtime::WedgeReport& report, const std::string& host_labels = "");
void count_wedge_event(Metrics& metrics, WedgeEvent event, const std::string& host_labels = "");
// At scrape time.
void refresh_wedge_gauges(Metrics& metrics, runtime::Wedges& wedges, const std::string& host_labels = "");

}  // namespace tether::serve
