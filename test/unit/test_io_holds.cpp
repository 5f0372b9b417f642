// The one hold finder (io/holds.h): its rule's duration, rows and tolerance, the phase markers, recordings.
#include <gtest/gtest.h>

#include <vector>

#include "piezo_compensation/io/holds.h"

using piezo::io::Dataset;
using piezo::io::find_holds;
using piezo::io::hold_rows;
using piezo::io::HoldRule;
using piezo::io::HoldRun;

namespace {

// One axis "c" at 1 Hz with the given voltages.
Dataset at_1hz(const std::vector<double>& v) {
  Dataset d;
  for (std::size_t i = 0; i < v.size(); ++i) d.time_s.push_back(static_cast<double>(i));
  auto& c = d.add_axis("c");
  c.voltage_v = v;
  c.position_nm.assign(v.size(), 0.0);
  return d;
}

std::vector<std::pair<std::size_t, std::size_t>> spans(const std::vector<HoldRun>& h) {
  std::vector<std::pair<std::size_t, std::size_t>> out;
  for (const auto& r : h) out.emplace_back(r.begin, r.end);
  return out;
}

using Spans = std::vector<std::pair<std::size_t, std::size_t>>;

}  // namespace

TEST(IoHolds, DurationAndAbsoluteTolerance) {
  // 4 rows at 1 V (one off by 0.5 µV), a step, 2 rows at 2 V, then 3 at 3 V.
  const Dataset d = at_1hz({1, 1 + 5e-7, 1, 1, 2, 2, 3, 3, 3});
  HoldRule r;
  r.min_duration_s = 3.0;
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{0, 4}, {6, 9}}));
  r.tolerance_v = 1e-7;  // the 0.5-µV row breaks the first run
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{6, 9}}));
  r.min_duration_s = 2.0;  // rows 2-3 and 4-5 now last long enough ...
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{2, 4}, {4, 6}, {6, 9}}));
  r.min_rows = 3;  // ... but have too few rows
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{6, 9}}));
}

TEST(IoHolds, ToleranceOfSpanAndFirstRowSkipped) {
  // Span 10 V: 1e-4 of it is 1 mV, so read-back noise of 0.5 mV still holds.
  const Dataset d = at_1hz({0, 5, 5.0005, 4.9995, 5, 10, 10, 10});
  HoldRule r;
  r.min_duration_s = 3.0;
  r.tolerance_v = 0.0;
  r.tolerance_of_span = 1e-4;
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{1, 5}, {5, 8}}));
  r.skip_first_row = true;
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{2, 5}, {6, 8}}));
  EXPECT_EQ(hold_rows(d.size(), find_holds(d, "c", r)), (std::vector<char>{0, 0, 1, 1, 1, 0, 1, 1}));
}

TEST(IoHolds, NeverAcrossARecordingStart) {
  Dataset d = at_1hz({1, 1, 1, 1, 1, 1});
  d.recordings = {{"first", 0, 0.0}, {"second", 3, 0.0}};
  HoldRule r;
  r.min_duration_s = 2.0;
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{0, 3}, {3, 6}}));
  EXPECT_EQ(spans(find_holds(d, "c", r, 1)), (Spans{{1, 3}, {3, 6}}));  // from row 1 on
}

TEST(IoHolds, PhaseMarkersDefineHoldsWhereTheDataHaveThem) {
  Dataset d = at_1hz({1, 1, 1, 1, 1, 1, 1});
  d.phase = {0, 1, 1, 1, 0, 1, 1};
  d.segment = {0, 0, 0, 1, 1, 1, 1};
  HoldRule r;
  r.min_duration_s = 100.0;  // the voltage rule would find none
  const auto h = find_holds(d, "c", r);
  EXPECT_EQ(spans(h), (Spans{{1, 3}, {3, 4}, {5, 7}}));  // a new run where the segment changes
  EXPECT_EQ(h[1].segment, 1);
  r.min_marked_s = 2.0;
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{1, 3}, {5, 7}}));
  r.use_phase = false;
  r.min_duration_s = 7.0;
  EXPECT_EQ(spans(find_holds(d, "c", r)), (Spans{{0, 7}}));
}
