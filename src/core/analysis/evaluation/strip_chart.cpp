#include "piezo_compensation/analysis/evaluation/strip_chart.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <utility>

#include "piezo_compensation/io/dataset.h"

namespace piezo::analysis {
namespace {

constexpr ChartColor kMeasured{0.35f, 0.75f, 1.0f, 0.85f};
constexpr ChartColor kPredicted{1.0f, 0.55f, 0.1f, 1.0f};
constexpr ChartColor kIntended{0.6f, 0.9f, 0.4f, 0.9f};
constexpr ChartColor kFused{0.95f, 0.95f, 0.95f, 1.0f};
constexpr ChartColor kFusedBand{0.85f, 0.85f, 0.95f, 0.35f};
constexpr ChartColor kFan{1.0f, 0.3f, 0.8f, 0.9f};
constexpr ChartColor kError{1.0f, 0.85f, 0.2f, 1.0f};
constexpr ChartColor kBand1{0.5f, 0.5f, 0.55f, 0.9f};
constexpr ChartColor kBand2{0.35f, 0.35f, 0.4f, 0.9f};
constexpr ChartColor kFrame{0.55f, 0.55f, 0.6f, 1.0f};
constexpr ChartColor kText{0.95f, 0.95f, 0.95f, 1.0f};

std::string fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

// A round span ≥ x (1, 2, 5 × 10^k) so that lane scales change in steps, not every frame.
double nice_ceil(double x) {
  if (!(x > 0.0) || !std::isfinite(x)) return 1.0;
  const double p = std::pow(10.0, std::floor(std::log10(x)));
  for (double m : {1.0, 2.0, 5.0, 10.0})
    if (m * p >= x) return m * p;
  return 10.0 * p;
}

ChartPrimitive prim(ChartPrimitive::Type t, std::string name, ChartColor c, double size) {
  ChartPrimitive p;
  p.type = t;
  p.name = std::move(name);
  p.color = c;
  p.size = size;
  return p;
}

ChartPrimitive text(std::string name, double x, double y, std::string s, double h, ChartColor c = kText) {
  auto p = prim(ChartPrimitive::Type::kText, std::move(name), c, h);
  p.x = {x};
  p.y = {y};
  p.text = std::move(s);
  return p;
}

}  // namespace

StripChart::StripChart(std::string axis, StripChartOptions options) : axis_(std::move(axis)), o_(options) {
  if (!(o_.window_s > 0.0)) throw std::invalid_argument("strip chart: window_s must be > 0 s");
}

void StripChart::add(ChartSample s) {
  if (!samples_.empty() && s.time_s < samples_.back().time_s) samples_.clear();
  samples_.push_back(std::move(s));
  while (!samples_.empty() && samples_.front().time_s < samples_.back().time_s - o_.window_s) samples_.pop_front();
}

StripChart::Stats StripChart::stats() const {
  Stats st;
  io::Dataset d;
  auto& ax = d.add_axis(axis_);
  std::vector<double> pred;
  double sum = 0.0;
  for (const auto& s : samples_) {
    if (!std::isfinite(s.measured_nm) || !std::isfinite(s.predicted_nm)) continue;
    d.time_s.push_back(s.time_s);
    ax.voltage_v.push_back(s.voltage_v);
    ax.position_nm.push_back(s.measured_nm);
    pred.push_back(s.predicted_nm);
    sum += std::abs(s.measured_nm - s.predicted_nm);
  }
  st.errors = pred.size();
  if (st.errors > 0) st.mae_nm = sum / static_cast<double>(st.errors);
  if (o_.noise_sigma_nm > 0.0) {
    st.floor = noise_floor_from_sigma(o_.noise_sigma_nm);
    st.floor_source = "given";
    return st;
  }
  if (st.errors >= o_.min_noise_samples) {
    st.floor = estimate_noise_floor(d, axis_, &pred);
    st.floor_source = "estimated (" + st.floor.method + ")";
  }
  // An encoder reading is off by up to half a step even without noise: σ ≥ q/√12, and a perfect predictor scores
  // q/4 when rounding dominates. estimate_noise_floor applies this with the step it sees; an axis held on one
  // step shows none, so the encoder's resolution (when given) is the bound.
  const bool given_q = o_.encoder_resolution_nm > 0.0;
  const double q = given_q ? o_.encoder_resolution_nm : st.floor.quantisation_nm;
  if (q > 0.0 && (st.errors > 0 || given_q) && st.floor.sigma_nm < q / std::sqrt(12.0) * (1.0 + 1e-9)) {
    st.floor.sigma_nm = q / std::sqrt(12.0);
    st.floor.floor_mae_nm = q / 4.0;
    st.floor.quantisation_nm = q;
    st.floor_source = fmt("q/sqrt12, q %g nm", q) + (given_q ? " encoder resolution" : " reading step");
  }
  return st;
}

namespace {

// The fused estimate: a thin line over its ±1σ band (translucent triangles between consecutive samples that both
// have a σ), under the predicted line so the model stays readable where the two agree.
template <class FX, class FY>
std::pair<ChartPrimitive, ChartPrimitive> fused_lane(const std::deque<ChartSample>& samples, const FX& X, const FY& Y,
                                                     const std::string& n) {
  using T = ChartPrimitive::Type;
  auto fused = prim(T::kLineStrip, n + "fused", kFused, 0.02);
  auto band = prim(T::kTriangleList, n + "fused_band", kFusedBand, 1.0);
  fused.z = 0.015, band.z = -0.01;
  const ChartSample* prev = nullptr;
  for (const auto& s : samples) {
    if (!std::isfinite(s.fused_nm)) {
      prev = nullptr;
      continue;
    }
    fused.x.push_back(X(s.time_s)), fused.y.push_back(Y(s.fused_nm));
    const bool has = std::isfinite(s.fused_sigma_nm) && s.fused_sigma_nm >= 0.0;
    if (has && prev) {
      const double xa = X(prev->time_s), xb = X(s.time_s);
      const double la = Y(prev->fused_nm - prev->fused_sigma_nm), ha = Y(prev->fused_nm + prev->fused_sigma_nm);
      const double lb = Y(s.fused_nm - s.fused_sigma_nm), hb = Y(s.fused_nm + s.fused_sigma_nm);
      band.x.insert(band.x.end(), {xa, xb, xb, xa, xb, xa});
      band.y.insert(band.y.end(), {la, lb, hb, la, hb, ha});
    }
    prev = has ? &s : nullptr;
  }
  return {fused, band};
}

// Drift fan: from the last prediction to each horizon (log-spaced to the right of "now").
template <class FY>
void draw_fan(const ChartSample& last_sample, const FY& Y, double x_right, double x_now, double fan_width,
              double lh, const std::string& n, std::vector<ChartPrimitive>& out) {
  using T = ChartPrimitive::Type;
  const ChartSample* last = &last_sample;
  if (std::isfinite(last->predicted_nm) && !last->drift_nm.empty() &&
      last->drift_nm.size() == last->drift_horizons_s.size()) {
    const double hmax = std::max(1.0, *std::max_element(last->drift_horizons_s.begin(), last->drift_horizons_s.end()));
    auto fan = prim(T::kLineList, n + "fan", kFan, 0.03);
    fan.z = 0.03;
    const std::size_t k = last->drift_nm.size();
    std::vector<double> label_y(k);
    for (std::size_t i = 0; i < k; ++i) {
      const double h = last->drift_horizons_s[i];
      const double xh = x_right + fan_width * std::log1p(std::max(h, 0.0)) / std::log1p(hmax);
      const double yh = Y(last->predicted_nm + last->drift_nm[i]);
      fan.x.insert(fan.x.end(), {x_now, xh});
      fan.y.insert(fan.y.end(), {Y(last->predicted_nm), yh});
      label_y[i] = yh;
    }
    // Labels in a column right of the fan, each at its line's end but pushed apart so none overlap (small drifts
    // end at nearly the same height).
    std::vector<std::size_t> order(k);
    for (std::size_t i = 0; i < k; ++i) order[i] = i;
    std::sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) { return label_y[a] > label_y[b]; });
    for (std::size_t j = 1; j < k; ++j)
      label_y[order[j]] = std::min(label_y[order[j]], label_y[order[j - 1]] - 1.3 * lh);
    for (std::size_t i = 0; i < k; ++i)
      out.push_back(text(n + "fan_label" + std::to_string(i), x_right + fan_width + 0.8, label_y[i],
                         fmt("%+.1f nm", last->drift_nm[i]) + fmt(" @%gs", last->drift_horizons_s[i]), lh, kFan));
    out.push_back(fan);
  }
}

// The headline: the axis, whether it is compensated, and the error against the noise floor.
std::string headline(const std::string& axis, const ChartSample* last, const StripChart::Stats& st) {
  std::string head = "axis " + axis;
  if (last) {
    head += last->fallback ? "   FALLBACK (uncorrected)"
                           : std::string(last->compensation_active ? "   compensation ON" : "   compensation OFF");
  } else {
    head += "   no data";
  }
  if (st.errors > 0) {
    head += fmt("   MAE %.1f nm", st.mae_nm);
    head += st.floor.sigma_nm > 0.0 ? fmt(" vs floor %.1f nm", st.floor.floor_mae_nm) +
                                          fmt(" (σ %.1f nm, ", st.floor.sigma_nm) + st.floor_source + ")"
                                    : std::string(" (floor: too few samples)");
  }
  return head;
}

// The frames of the position and error lanes (top and bottom of each) and the error lane's zero line.
ChartPrimitive lane_frames(const std::string& n, double x0, double W, std::pair<double, double> pos,
                           std::pair<double, double> err, double y_err_mid) {
  auto frame = prim(ChartPrimitive::Type::kLineList, n + "frame", kFrame, 0.015);
  for (const auto& [yt, yb] : {pos, err}) {
    const double xs[] = {x0, x0 + W, x0 + W, x0 + W, x0 + W, x0, x0, x0};
    const double ys[] = {yt, yt, yt, yb, yb, yb, yb, yt};
    frame.x.insert(frame.x.end(), xs, xs + 8);
    frame.y.insert(frame.y.end(), ys, ys + 8);
  }
  frame.x.insert(frame.x.end(), {x0, x0 + W});  // error zero line
  frame.y.insert(frame.y.end(), {y_err_mid, y_err_mid});
  return frame;
}

// The ±1σ and ±2σ bands of the noise floor in the error lane (YE: error [nm] → lane height), with their labels.
template <class F>
void noise_bands(const std::string& n, double x0, double W, double sigma_nm, double lh, const F& YE,
                 std::vector<ChartPrimitive>& out) {
  for (int k : {2, 1}) {
    auto b = prim(ChartPrimitive::Type::kLineList, n + "band" + std::to_string(k), k == 1 ? kBand1 : kBand2, 0.015);
    for (double sgn : {-1.0, 1.0}) {
      b.x.insert(b.x.end(), {x0, x0 + W});
      b.y.insert(b.y.end(), {YE(sgn * k * sigma_nm), YE(sgn * k * sigma_nm)});
    }
    out.push_back(b);
    out.push_back(text(n + "band_label" + std::to_string(k), x0 + W + 0.25, YE(k * sigma_nm),
                       "±" + std::to_string(k) + "σ", lh, k == 1 ? kBand1 : kBand2));
  }
}

}  // namespace

std::vector<ChartPrimitive> StripChart::draw(double x0, double y0) const {
  using T = ChartPrimitive::Type;
  std::vector<ChartPrimitive> out;
  const std::string n = axis_ + "/";
  const double W = o_.width, H = o_.position_height, E = o_.error_height;
  const double th = o_.text_height, lh = 0.7 * th;  // headline, labels
  const double y_text = y0 - 0.6 * th, y_model = y_text - 1.2 * th, y_pos_top = y0 - 3.2 * th, y_pos_bot = y_pos_top - H;
  const double y_err_top = y_pos_bot - 0.3, y_err_mid = y_err_top - E / 2, y_err_bot = y_err_top - E;
  const double t_now = samples_.empty() ? 0.0 : samples_.back().time_s;
  const auto X = [&](double t) { return x0 + W * (1.0 - (t_now - t) / o_.window_s); };
  const Stats st = stats();

  // Position lane scale: everything drawn in it, including the fan's ends.
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  const auto grow = [&](double v) {
    if (std::isfinite(v)) lo = std::min(lo, v), hi = std::max(hi, v);
  };
  for (const auto& s : samples_) {
    grow(s.measured_nm), grow(s.predicted_nm), grow(s.intended_nm), grow(s.fused_nm);
    if (std::isfinite(s.fused_sigma_nm)) grow(s.fused_nm + s.fused_sigma_nm), grow(s.fused_nm - s.fused_sigma_nm);
  }
  const ChartSample* last = samples_.empty() ? nullptr : &samples_.back();
  if (last && std::isfinite(last->predicted_nm))
    for (double d : last->drift_nm) grow(last->predicted_nm + d);
  if (!std::isfinite(lo)) lo = 0.0, hi = 0.0;
  const double span = nice_ceil(std::max(hi - lo, 10.0) * 1.1);
  const double mid = 0.5 * (lo + hi);
  const double p_lo = mid - span / 2;
  const auto Y = [&](double nm) { return y_pos_bot + H * (nm - p_lo) / span; };

  // Error lane: ± (3σ, or the largest error when bigger), rounded.
  double emax = st.floor.sigma_nm * 3.0;
  for (const auto& s : samples_)
    if (std::isfinite(s.measured_nm) && std::isfinite(s.predicted_nm))
      emax = std::max(emax, std::abs(s.measured_nm - s.predicted_nm));
  const double ehalf = nice_ceil(std::max(emax, 1.0));
  const auto YE = [&](double nm) { return y_err_mid + (E / 2) * std::clamp(nm / ehalf, -1.0, 1.0); };

  // Frames of both lanes and the "now" line.
  out.push_back(lane_frames(n, x0, W, {y_pos_top, y_pos_bot}, {y_err_top, y_err_bot}, y_err_mid));

  // Noise-floor bands in the error lane.
  if (st.floor.sigma_nm > 0.0) noise_bands(n, x0, W, st.floor.sigma_nm, lh, YE, out);

  // Layers: measured dots at the bottom, the predicted line over them (wider than a dot is tall, so it stays
  // visible where the dots sit on it), the intended target thin on top.
  auto meas = prim(T::kPoints, n + "measured", kMeasured, 0.035);
  auto pred = prim(T::kLineStrip, n + "predicted", kPredicted, 0.045);
  auto intent = prim(T::kLineStrip, n + "intended", kIntended, 0.015);
  auto err = prim(T::kPoints, n + "error", kError, 0.04);
  meas.z = 0.0, pred.z = 0.01, intent.z = 0.02, err.z = 0.01;  // intended: thin, over the predicted line it
                                                                 // follows when compensating
  for (const auto& s : samples_) {
    const double x = X(s.time_s);
    if (std::isfinite(s.measured_nm)) meas.x.push_back(x), meas.y.push_back(Y(s.measured_nm));
    if (std::isfinite(s.predicted_nm)) pred.x.push_back(x), pred.y.push_back(Y(s.predicted_nm));
    if (std::isfinite(s.intended_nm)) intent.x.push_back(x), intent.y.push_back(Y(s.intended_nm));
    if (std::isfinite(s.measured_nm) && std::isfinite(s.predicted_nm))
      err.x.push_back(x), err.y.push_back(YE(s.measured_nm - s.predicted_nm));
  }
  auto [fused, band] = fused_lane(samples_, X, Y, n);
  if (!band.x.empty()) out.push_back(band);
  // rviz refuses an empty or one-point line strip: only emit what can be drawn.
  for (auto* p : {&intent, &pred, &fused})
    if (p->x.size() >= 2) out.push_back(*p);
  for (auto* p : {&meas, &err})
    if (!p->x.empty()) out.push_back(*p);

  if (last) draw_fan(*last, Y, x0 + W, X(t_now), o_.fan_width, lh, n, out);

  // Scale labels and the headline.
  const double xl = x0 - 5 * lh;
  out.push_back(text(n + "pos_hi", xl, y_pos_top, fmt("%.0f nm", p_lo + span), lh));
  out.push_back(text(n + "pos_lo", xl, y_pos_bot, fmt("%.0f nm", p_lo), lh));
  out.push_back(text(n + "pos_title", xl, y_pos_bot + H / 2, "position", lh));
  out.push_back(text(n + "err_hi", xl, y_err_top, fmt("%+.0f nm", ehalf), lh, kError));
  out.push_back(text(n + "err_lo", xl, y_err_bot, fmt("%+.0f nm", -ehalf), lh, kError));
  out.push_back(text(n + "err_title", xl, y_err_mid, "error", lh, kError));
  out.push_back(text(n + "t_left", x0, y_err_bot - 1.2 * lh, fmt("-%.0f s", o_.window_s), lh));
  out.push_back(text(n + "t_now", x0 + W, y_err_bot - 1.2 * lh, "now", lh));
  out.push_back(text(n + "legend", x0 + W / 2, y_err_bot - 1.2 * lh,
                     std::string("dots measured   orange predicted   green intended") +
                         (fused.x.size() >= 2 ? "   white fused ±1σ" : "") +
                         "   magenta drift forecast   yellow measured - predicted",
                     lh));
  if (last)
    out.push_back(text(n + "model", x0 + W / 2, y_model,
                       "model " + last->model + (last->fallback ? "   " + last->status : std::string()), lh));
  const std::string head = headline(axis_, last, st);
  out.push_back(text(n + "headline", x0 + W / 2, y_text, head, th));
  return out;
}

}  // namespace piezo::analysis
