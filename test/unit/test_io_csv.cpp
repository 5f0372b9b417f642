#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include "piezo_compensation/io/dataset.h"

using piezo::io::DataError;
using piezo::io::Dataset;
using piezo::io::read_csv;
using piezo::io::write_csv;
using piezo::io::time_base;
using piezo::io::TimeBase;

namespace {

std::string write_file(const std::string& name, const std::string& text) {
  std::string path = ::testing::TempDir() + name;
  std::ofstream(path) << text;
  return path;
}

// The error message of reading `text`, or "" if it parsed.
std::string error_of(const std::string& text) {
  try {
    read_csv(write_file("bad.csv", text));
  } catch (const DataError& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST(Csv, RoundTripKeepsAllColumns) {
  Dataset d;
  d.time_s = {0.0, 0.1, 0.2};
  auto& c = d.add_axis("c");
  c.voltage_v = {1.0, 2.5, -80.0};
  c.position_nm = {10.0, 20.0, -1000.125};
  c.true_position_nm = {11.0, 21.0, -1001.0};
  d.aux.push_back({"temperature_c", {21.0, 21.1, 21.2}});
  d.segment = {0, 0, 1};
  d.phase = {0, 1, 1};
  const std::string path = ::testing::TempDir() + "rt.csv";
  write_csv(path, d);
  const Dataset r = read_csv(path);
  ASSERT_EQ(r.size(), 3u);
  ASSERT_TRUE(r.has_axis("c"));
  EXPECT_FALSE(r.has_axis("a"));
  EXPECT_EQ(r.axis("c").voltage_v, c.voltage_v);
  EXPECT_EQ(r.axis("c").position_nm, c.position_nm);
  EXPECT_EQ(r.axis("c").true_position_nm, c.true_position_nm);
  ASSERT_NE(r.find_aux("temperature_c"), nullptr);
  EXPECT_EQ(r.find_aux("temperature_c")->values, d.aux[0].values);
  EXPECT_EQ(r.segment, d.segment);
  EXPECT_EQ(r.phase, d.phase);
  EXPECT_NEAR(r.sample_rate_hz(), 10.0, 1e-9);
}

TEST(Csv, AnyConstantRateAndAxisOrder) {
  const Dataset d = read_csv(write_file("rate.csv", "c_position_nm,time_s,c_voltage_v\n5,0,1\n6,0.02,2\n7,0.04,3\n"));
  EXPECT_NEAR(d.sample_rate_hz(), 50.0, 1e-6);
  EXPECT_EQ(d.axis("c").position_nm[2], 7.0);
}

TEST(Csv, MalformedFilesNameFileRowAndColumn) {
  EXPECT_NE(error_of("c_voltage_v,c_position_nm\n1,2\n").find("missing column time_s"), std::string::npos);
  EXPECT_NE(error_of("time_s,c_voltage_v\n0,1\n").find("missing column c_position_nm"), std::string::npos);
  EXPECT_NE(error_of("time_s,temperature_c\n0,1\n").find("missing axis columns"), std::string::npos);
  const std::string nn = error_of("time_s,c_voltage_v,c_position_nm\n0,1,2\n0.1,abc,3\n");
  EXPECT_NE(nn.find("row 3, column c_voltage_v: not a number: 'abc'"), std::string::npos) << nn;
  EXPECT_NE(nn.find("bad.csv"), std::string::npos) << nn;
  const std::string nan = error_of("time_s,c_voltage_v,c_position_nm\n0,1,2\n0.1,1,nan\n");
  EXPECT_NE(nan.find("row 3, column c_position_nm"), std::string::npos) << nan;
  EXPECT_NE(nan.find("not a finite number"), std::string::npos) << nan;
  const std::string time = error_of("time_s,c_voltage_v,c_position_nm\n0,1,2\n0.1,1,2\n0.1,1,2\n");
  EXPECT_NE(time.find("row 4, column time_s: time does not increase"), std::string::npos) << time;
  const std::string shortrow = error_of("time_s,c_voltage_v,c_position_nm\n0,1,2\n0.1,1\n");
  EXPECT_NE(shortrow.find("row 3, column c_position_nm: missing value"), std::string::npos) << shortrow;
  const std::string longrow = error_of("time_s,c_voltage_v,c_position_nm\n0,1,2,3\n");
  EXPECT_NE(longrow.find("row 2: more cells"), std::string::npos) << longrow;
  const std::string empty = error_of("time_s,c_voltage_v,c_position_nm\n0,,2\n");
  EXPECT_NE(empty.find("row 2, column c_voltage_v: empty cell"), std::string::npos) << empty;
  EXPECT_NE(error_of("").find("file is empty"), std::string::npos);
  EXPECT_NE(error_of("time_s,c_voltage_v,c_position_nm\n").find("no data rows"), std::string::npos);
}

// A host clock: jittered steps and late rows are accepted as they are (one model step per row at the median step),
// and the time a model steps over is reported; a step longer than kMaxStepS is one error naming the row.
TEST(Csv, HostClockJitterAndLateRowsAreSteppedOverAndReported) {
  std::string text = "time_s,c_voltage_v,c_position_nm\n";
  std::vector<double> t;
  for (int i = 0; i < 40; ++i) t.push_back(0.1 * i + (i % 3 == 1 ? 0.012 : 0.0) + (i >= 30 ? 0.3 : 0.0));
  for (double x : t) text += std::to_string(x) + ",1,2\n";
  const Dataset d = read_csv(write_file("jitter.csv", text));
  EXPECT_NEAR(d.sample_period_s(), 0.1, 1e-9);
  const TimeBase tb = time_base(d.time_s);
  EXPECT_FALSE(tb.constant);
  EXPECT_EQ(tb.late_steps, 1u);
  EXPECT_EQ(tb.longest_row, 30u);
  EXPECT_NEAR(tb.longest_step_s, 0.4, 1e-9);
  EXPECT_NEAR(tb.late_s, 0.3, 1e-9);
  EXPECT_NEAR(tb.clock_lag_s, t.back() - t.front() - 39 * 0.1, 1e-9);
  EXPECT_GT(tb.jitter_s, 0.005);
  EXPECT_LT(tb.jitter_s, 0.012);
  EXPECT_NEAR(tb.mean_step_s, (t.back() - t.front()) / 39.0, 1e-12);
  // a sample clock is constant
  std::vector<double> clock;
  for (int i = 0; i < 20; ++i) clock.push_back(i / 11.0);
  EXPECT_TRUE(time_base(clock).constant);
  EXPECT_EQ(time_base(clock).late_steps, 0u);

  // A gap the model cannot step over is named where it is.
  text = "time_s,c_voltage_v,c_position_nm\n";
  for (int i = 0; i < 40; ++i) text += std::to_string(0.1 * i + (i >= 30 ? 12.0 : 0.0)) + ",1,2\n";
  try {
    read_csv(write_file("gap.csv", text)).sample_rate_hz();
    FAIL() << "expected DataError";
  } catch (const DataError& e) {
    EXPECT_NE(std::string(e.what()).find("row 32, column time_s: a gap of 12.1 s"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("usual step 0.1 s"), std::string::npos) << e.what();
  }
}

TEST(Csv, MissingFileIsOneClearError) {
  try {
    read_csv("/nonexistent/dir/x.csv");
    FAIL();
  } catch (const DataError& e) {
    EXPECT_EQ(std::string(e.what()), "/nonexistent/dir/x.csv: cannot open file");
  }
}

TEST(Dataset, SliceAndAppendAreInverse) {
  Dataset d;
  for (int i = 0; i < 10; ++i) d.time_s.push_back(i * 0.5);
  auto& c = d.add_axis("c");
  for (int i = 0; i < 10; ++i) {
    c.voltage_v[i] = i;
    c.position_nm[i] = 2.0 * i;
  }
  Dataset a = d.slice(0, 4);
  a.append(d.slice(4, 10));
  EXPECT_EQ(a.time_s, d.time_s);
  EXPECT_EQ(a.axis("c").position_nm, d.axis("c").position_nm);
  EXPECT_THROW(a.append(d.slice(0, 2)), DataError);  // time would go backwards
}
