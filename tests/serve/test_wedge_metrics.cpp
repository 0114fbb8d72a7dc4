// The wedge metric tables: each series declared once, listed at zero only for the wedges that are on, and fed by
// reports, events and gauges as /metrics shows them.
#include <gtest/gtest.h>

#include <set>

#include "serve/wedge_metrics.h"

using namespace tether;
using namespace tether::serve;

namespace {

bool shows(const std::string& rendered, const std::string& line) {
  return rendered.find(line + "\n") != std::string::npos;
}

}  // namespace

TEST(WedgeMetrics, EachSeriesIsDeclaredOnceWithItsHelp) {
  std::set<std::pair<std::string, std::string>> series;
  for (const auto& c : wedge_counters()) {
    EXPECT_TRUE(series.insert({c.name, c.labels}).second) << c.name << "{" << c.labels << "}";
    EXPECT_NE(std::string(c.help), "") << c.name;
    EXPECT_EQ(c.from_report != nullptr, !c.event.has_value()) << c.name << ": fed by a report or by an event, not both";
  }
  for (const auto& g : wedge_gauges()) EXPECT_TRUE(series.insert({g.name, ""}).second) << g.name;
}

TEST(WedgeMetrics, OnlyEnabledWedgesAreListedAtZero) {
  runtime::WedgeOptions o;
  {
    Metrics m("v", "");
    runtime::Wedges w(o);
    register_wedge_metrics(m, w);
    EXPECT_EQ(m.render().find("tether_deadline_exceeded_total"), std::string::npos);
    EXPECT_EQ(m.render().find("tether_fallback_total"), std::string::npos);
  }
  o.deadline_ms = 50;
  o.cloud_fallback = "http://cloud";
  o.sampler.adaptive_threshold = 0.1f;
  o.sampler.rtc = true;
  o.max_consecutive_crashes = 3;
  o.similarity_threshold = 0.1;
  o.max_similar_skips = 2;
  Metrics m("v", "");
  runtime::Wedges w(o);
  register_wedge_metrics(m, w);
  const std::string r = m.render();
  for (const char* line : {"tether_deadline_exceeded_total 0", "tether_fallback_total{outcome=\"success\"} 0",
                           "tether_fallback_total{outcome=\"failure\"} 0", "tether_denoise_steps_total 0",
                           "tether_rtc_total 0", "tether_circuit_rejected_total 0", "tether_action_skip_total 0"})
    EXPECT_TRUE(shows(r, line)) << line << "\n" << r;
  EXPECT_TRUE(shows(r, "# HELP tether_deadline_exceeded_total Requests that missed --deadline-ms."));
  EXPECT_EQ(r.find("tether_denoise_runs_total"), std::string::npos) << "appears with its first count only";
  EXPECT_EQ(r.find("tether_guard_clamped_total"), std::string::npos) << "no guard without an embodiment";
}

TEST(WedgeMetrics, AReportFeedsOnlyTheCountersItsFieldsSet) {
  Metrics m("v", "");
  runtime::WedgeReport report;
  count_wedge_report(m, report);
  EXPECT_EQ(m.render().find("tether_"), m.render().find("tether_requests_total")) << "an empty report counts nothing";
  report.guard.clamped = true;
  report.guard.violations.push_back({0, "j1", "velocity", 3, 1});
  report.guard.violations.push_back({1, "j1", "velocity", 3, 1});
  report.skipped = true;
  report.source = runtime::ActionSource::last_good;
  report.denoise_steps_used = 4;
  report.rtc_applied = true;
  count_wedge_report(m, report);
  count_wedge_report(m, report);
  const std::string r = m.render();
  for (const char* line : {"tether_guard_clamped_total 2", "tether_guard_violations_total{joint=\"j1\",limit=\"velocity\"} 4",
                           "tether_action_skip_total 2", "tether_last_good_chunk_total 2", "tether_denoise_steps_total 8",
                           "tether_denoise_runs_total 2", "tether_rtc_total 2"})
    EXPECT_TRUE(shows(r, line)) << line << "\n" << r;
}

TEST(WedgeMetrics, EventsAndGauges) {
  Metrics m("v", "");
  count_wedge_event(m, WedgeEvent::fallback_failure);
  count_wedge_event(m, WedgeEvent::fallback_failure);
  count_wedge_event(m, WedgeEvent::circuit_rejected);
  runtime::WedgeOptions o;
  o.max_consecutive_crashes = 2;
  o.inject_latency_ms = 25;
  runtime::Wedges w(o);
  refresh_wedge_gauges(m, w);
  const std::string r = m.render();
  for (const char* line : {"tether_fallback_total{outcome=\"failure\"} 2", "tether_circuit_rejected_total 1",
                           "tether_circuit_open 0", "tether_circuit_opened_total 0", "tether_consecutive_failures 0",
                           "tether_injected_latency_ms 25", "tether_episodes 0", "# TYPE tether_circuit_open gauge"})
    EXPECT_TRUE(shows(r, line)) << line << "\n" << r;
  EXPECT_EQ(r.find("outcome=\"success\""), std::string::npos);
  EXPECT_EQ(r.find("tether_trace_lines_total"), std::string::npos) << "no recorder, no trace gauges";
}

TEST(WedgeMetrics, AHostsLabelsComeFirstInEverySeries) {
  Metrics m("v", "");
  const std::string arm = "embodiment=\"arm\"";
  runtime::WedgeReport report;
  report.guard.clamped = true;
  report.guard.violations.push_back({0, "j1", "velocity", 3, 1});
  count_wedge_report(m, report, arm);
  count_wedge_event(m, WedgeEvent::fallback_success, arm);
  runtime::WedgeOptions o;
  o.max_consecutive_crashes = 2;
  runtime::Wedges w(o);
  refresh_wedge_gauges(m, w, arm);
  register_wedge_metrics(m, w, "embodiment=\"humanoid\"");
  const std::string r = m.render();
  for (const char* line : {"tether_guard_clamped_total{embodiment=\"arm\"} 1",
                           "tether_guard_violations_total{embodiment=\"arm\",joint=\"j1\",limit=\"velocity\"} 1",
                           "tether_fallback_total{embodiment=\"arm\",outcome=\"success\"} 1",
                           "tether_circuit_open{embodiment=\"arm\"} 0",
                           "tether_circuit_rejected_total{embodiment=\"humanoid\"} 0"})
    EXPECT_TRUE(shows(r, line)) << line << "\n" << r;
}
