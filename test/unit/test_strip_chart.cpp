// The strip chart's window, statistics and layout (analysis/evaluation/strip_chart.h).
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "piezo_compensation/analysis/evaluation/strip_chart.h"

namespace {

using piezo::analysis::ChartPrimitive;
using piezo::analysis::ChartSample;
using piezo::analysis::StripChart;
using piezo::analysis::StripChartOptions;

// A held voltage with true position 1000 nm, an encoder with 20 nm steps and σ = 8 nm noise, a model 15 nm off.
ChartSample sample(double t, std::mt19937& rng, double noise_nm = 8.0) {
  std::normal_distribution<double> n(0.0, noise_nm);
  ChartSample s;
  s.time_s = t;
  s.voltage_v = 40.0;
  s.measured_nm = 20.0 * std::round((1000.0 + n(rng)) / 20.0);
  s.predicted_nm = 985.0;
  s.intended_nm = 990.0;
  s.drift_horizons_s = {10, 60, 600};
  s.drift_nm = {1.0, 3.0, 8.0};
  s.compensation_active = true;
  s.model = "mm3e_sim_c.yaml (pi_creep_fractional)";
  return s;
}

const ChartPrimitive* find(const std::vector<ChartPrimitive>& ps, const std::string& name) {
  for (const auto& p : ps)
    if (p.name == name) return &p;
  return nullptr;
}

TEST(StripChart, KeepsOnlyTheWindowAndRestartsOnATimeJump) {
  StripChartOptions o;
  o.window_s = 10.0;
  StripChart c("c", o);
  std::mt19937 rng(1);
  for (int i = 0; i <= 300; ++i) c.add(sample(i * 0.1, rng));
  EXPECT_EQ(c.size(), 101u);  // 20.0 … 30.0 s
  c.add(sample(5.0, rng));    // a bag loop / simulator restart
  EXPECT_EQ(c.size(), 1u);
}

TEST(StripChart, MaeAndNoiseFloorFromTheWindow) {
  StripChart c("c", StripChartOptions{});
  std::mt19937 rng(7);
  for (int i = 0; i < 660; ++i) c.add(sample(i / 11.0, rng));
  const auto st = c.stats();
  EXPECT_EQ(st.errors, 660u);
  // measured − predicted ≈ 15 nm + noise: MAE near 15 (noise adds a little), floor σ near max(8, 20/√12) = 8.
  EXPECT_NEAR(st.mae_nm, 16.0, 2.5);
  EXPECT_NEAR(st.floor.sigma_nm, 8.0, 1.5);
  EXPECT_NEAR(st.floor.quantisation_nm, 20.0, 1e-9);

  StripChartOptions given;
  given.noise_sigma_nm = 20.8;
  StripChart g("c", given);
  for (int i = 0; i < 5; ++i) g.add(sample(i, rng));
  EXPECT_DOUBLE_EQ(g.stats().floor.sigma_nm, 20.8);
}

TEST(StripChart, LayoutHasEveryElementInsideItsLane) {
  StripChartOptions o;
  StripChart c("b", o);
  std::mt19937 rng(3);
  for (int i = 0; i < 200; ++i) c.add(sample(i / 11.0, rng));
  const auto ps = c.draw(0.0, 0.0);
  for (const char* name : {"b/measured", "b/predicted", "b/intended", "b/error", "b/fan", "b/band1", "b/band2",
                           "b/headline", "b/model", "b/frame"})
    ASSERT_NE(find(ps, name), nullptr) << name;
  EXPECT_EQ(find(ps, "b/measured")->x.size(), 200u);
  EXPECT_EQ(find(ps, "b/fan")->x.size(), 6u);  // a segment per horizon
  // Newest sample at the right edge (x = width), all within [0, width].
  for (double x : find(ps, "b/measured")->x) EXPECT_TRUE(x >= -1e-9 && x <= o.width + 1e-9) << x;
  EXPECT_NEAR(find(ps, "b/measured")->x.back(), o.width, 1e-9);
  // Fan right of "now", ordered by horizon.
  const auto& fan = *find(ps, "b/fan");
  EXPECT_LT(fan.x[1], fan.x[3]);
  EXPECT_LT(fan.x[3], fan.x[5]);
  EXPECT_LE(fan.x[5], o.width + o.fan_width + 1e-9);
  // The error lane lies below the position lane and holds every error point.
  double pos_min = 1e9, err_max = -1e9;
  for (double y : find(ps, "b/measured")->y) pos_min = std::min(pos_min, y);
  for (double y : find(ps, "b/error")->y) err_max = std::max(err_max, y);
  EXPECT_LT(err_max, pos_min);
  for (double y : find(ps, "b/error")->y) EXPECT_GE(y, -c.height());
  const auto& head = find(ps, "b/headline")->text;
  EXPECT_NE(head.find("compensation ON"), std::string::npos) << head;
  EXPECT_NE(head.find("MAE"), std::string::npos) << head;
  ASSERT_NE(find(ps, "b/model"), nullptr);
  EXPECT_NE(find(ps, "b/model")->text.find("mm3e_sim_c.yaml"), std::string::npos);
}

// A held axis on a coarse encoder: every reading sits on the same 250 nm step, so the window shows no spread. The
// floor falls back to the quantisation bound q/√12 with q the encoder's resolution, and the headline says so.
TEST(StripChart, HeldAxisOnACoarseEncoderUsesTheQuantisationFloor) {
  std::mt19937 rng(11);
  const auto held = [&](StripChart& c) {
    for (int i = 0; i < 200; ++i) {
      auto s = sample(i / 11.0, rng, 0.0);
      s.measured_nm = 1000.0;  // one 250 nm step
      s.predicted_nm = 1040.0;
      c.add(s);
    }
  };
  StripChart unknown("a", StripChartOptions{});
  held(unknown);
  EXPECT_EQ(unknown.stats().floor.sigma_nm, 0.0);  // nothing in the readings tells the step

  StripChartOptions o;
  o.encoder_resolution_nm = 250.0;
  StripChart c("a", o);
  held(c);
  const auto st = c.stats();
  EXPECT_NEAR(st.floor.sigma_nm, 250.0 / std::sqrt(12.0), 1e-9);  // 72.2 nm
  EXPECT_NEAR(st.floor.floor_mae_nm, 62.5, 1e-9);                 // q/4
  const auto ps = c.draw(0, 0);
  const auto& head = find(ps, "a/headline")->text;
  EXPECT_NE(head.find("q/sqrt12, q 250 nm encoder resolution"), std::string::npos) << head;
  ASSERT_NE(find(ps, "a/band1"), nullptr);  // the bands have a width: the floor is the quantiser's

  // A noisy axis above the bound keeps its estimate (the 20 nm encoder with σ 8 nm: 8 > 20/√12).
  StripChartOptions oc;
  oc.encoder_resolution_nm = 20.0;
  StripChart n("c", oc);
  for (int i = 0; i < 660; ++i) n.add(sample(i / 11.0, rng));
  EXPECT_NEAR(n.stats().floor.sigma_nm, 8.0, 1.5);
  EXPECT_NE(n.stats().floor_source.find("estimated"), std::string::npos);
}

TEST(StripChart, PredictedLineIsDrawnOverTheMeasuredDots) {
  StripChart c("c", StripChartOptions{});
  std::mt19937 rng(2);
  for (int i = 0; i < 100; ++i) c.add(sample(i / 11.0, rng));
  const auto ps = c.draw(0, 0);
  const auto* meas = find(ps, "c/measured");
  const auto* pred = find(ps, "c/predicted");
  ASSERT_TRUE(meas && pred);
  EXPECT_GT(pred->z, meas->z);
  EXPECT_GT(pred->size, meas->size);  // wider than a dot: visible where the dots sit on it
  EXPECT_GT(find(ps, "c/intended")->z, meas->z);
}

TEST(StripChart, FallbackAndEmptyChartsSaySo) {
  StripChart c("a", StripChartOptions{});
  EXPECT_NE(find(c.draw(0, 0), "a/headline")->text.find("no data"), std::string::npos);
  std::mt19937 rng(5);
  auto s = sample(0.0, rng);
  s.fallback = true;
  s.predicted_nm = std::nan("");
  s.status = "model unavailable: broken.yaml";
  c.add(s);
  const auto ps = c.draw(0, 0);
  EXPECT_NE(find(ps, "a/headline")->text.find("FALLBACK"), std::string::npos);
  EXPECT_EQ(find(ps, "a/predicted"), nullptr);  // nothing to draw, no one-point strip
  EXPECT_EQ(find(ps, "a/fan"), nullptr);
}

// The fused estimate (Prediction.fused_position / _sigma): a line inside a ±1σ band of filled triangles, in the
// position lane; none without it (a model file with no estimator block publishes NaN).
TEST(StripChart, FusedPositionIsALineInItsSigmaBand) {
  StripChart plain("c", StripChartOptions{});
  std::mt19937 rng(3);
  for (int i = 0; i < 50; ++i) plain.add(sample(i / 11.0, rng));
  auto ps = plain.draw(0, 0);
  EXPECT_EQ(find(ps, "c/fused"), nullptr);
  EXPECT_EQ(find(ps, "c/fused_band"), nullptr);
  EXPECT_EQ(find(ps, "c/legend")->text.find("fused"), std::string::npos);

  StripChart c("c", StripChartOptions{});
  const int n = 200;
  for (int i = 0; i < n; ++i) {
    auto s = sample(i / 11.0, rng);
    if (i >= 20) {  // the first samples without an estimate (before the predictor had one)
      s.fused_nm = 998.0 + 0.01 * i;
      s.fused_sigma_nm = i < 100 ? 12.0 : 1.5;  // tightens as readings average
    }
    c.add(s);
  }
  ps = c.draw(0, 0);
  const auto* fused = find(ps, "c/fused");
  const auto* band = find(ps, "c/fused_band");
  const auto* meas = find(ps, "c/measured");
  ASSERT_TRUE(fused && band && meas);
  EXPECT_EQ(fused->type, ChartPrimitive::Type::kLineStrip);
  EXPECT_EQ(band->type, ChartPrimitive::Type::kTriangleList);
  EXPECT_EQ(fused->x.size(), static_cast<std::size_t>(n - 20));
  EXPECT_EQ(band->x.size(), 6u * (n - 21));  // two triangles between each pair of samples with a σ
  EXPECT_EQ(band->x.size(), band->y.size());
  EXPECT_LT(band->z, meas->z);   // under the dots and lines
  EXPECT_GT(fused->z, meas->z);  // the line over the dots
  EXPECT_NE(find(ps, "c/legend")->text.find("fused"), std::string::npos);
  // The band's edges are fused ∓ σ on the lane's scale: the lane maps nm linearly, so the band's height in chart
  // units is 2σ × (lane height / span), the same for every sample with the same σ, and it contains the line.
  const auto height_at = [&](std::size_t tri) {  // first triangle of pair `tri`: (xa, la), (xb, lb), (xb, hb)
    return band->y[6 * tri + 2] - band->y[6 * tri + 1];
  };
  const double wide = height_at(10), narrow = height_at(150);
  EXPECT_NEAR(wide / narrow, 12.0 / 1.5, 1e-6);
  for (std::size_t k = 0; k + 1 < fused->y.size(); ++k) {
    const double lo = band->y[6 * k + 1], hi = band->y[6 * k + 2];
    EXPECT_LT(lo, fused->y[k + 1]);
    EXPECT_GT(hi, fused->y[k + 1]);
  }
  // everything inside the position lane
  const double top = -3.2 * StripChartOptions{}.text_height, bottom = top - StripChartOptions{}.position_height;
  for (double y : band->y) EXPECT_TRUE(y <= top + 1e-9 && y >= bottom - 1e-9) << y;

  // A gap in the estimate (NaN) breaks the band: no triangle bridges it.
  StripChart g("c", StripChartOptions{});
  for (int i = 0; i < 30; ++i) {
    auto s = sample(i / 11.0, rng);
    s.fused_nm = i == 15 ? std::nan("") : 1000.0;
    s.fused_sigma_nm = 2.0;
    g.add(s);
  }
  EXPECT_EQ(find(g.draw(0, 0), "c/fused_band")->x.size(), 6u * (30 - 3));
}

}  // namespace
