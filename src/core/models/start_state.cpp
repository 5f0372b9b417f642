#include "piezo_compensation/models/start_state.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>
#include <vector>

#include <Eigen/Dense>

#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/util/format.h"

namespace piezo::models {

namespace {
// The margin of the search (the header): candidates within kStartMargin·ln(n_eff) of the best fit count as equally
// good. Measured on the stage matrix's separate recordings, seeds 22–24: 4–16 give the same pass counts within ±5 %.
constexpr double kStartMargin = 8.0;

using util::fmt;

// Rows of the window: those with time − t0 < window_s (at least one).
std::size_t window_rows(const io::Dataset& data, double window_s) {
  std::size_t k = 0;
  while (k < data.size() && data.time_s[k] - data.time_s[0] < window_s) ++k;
  return std::max<std::size_t>(k, 1);
}

void check_window(const io::Dataset& data, const std::string& axis, double window_s, std::size_t k) {
  const io::AxisSeries& ax = data.axis(axis);
  if (k >= data.size())
    throw io::DataError(data.source_or_data() + ": the start window of " + fmt(window_s, 6) +
                        " s covers the whole data set; nothing is left after it");
  for (std::size_t i = 0; i < k; ++i) {
    if (!std::isfinite(ax.voltage_v[i]))
      throw io::DataError(data.source_or_data() + ": the start window holds a non-finite voltage at row " + std::to_string(i + 1));
    if (!std::isfinite(ax.position_nm[i]))
      throw io::DataError(data.source_or_data() + ": the start window holds a non-finite measured position at row " +
                          std::to_string(i + 1) + " (the window needs every reading)");
  }
}

void run_rows(Model& m, double from_v, double to_v, std::size_t n, const double* aux) {
  for (std::size_t j = 1; j <= n; ++j) {
    const ModelInput in{from_v + (to_v - from_v) * static_cast<double>(j) / static_cast<double>(n), aux};
    const double y = m.predict(in);
    m.commit(in, std::isfinite(y) ? y : 0.0);
  }
}

// The window's typical voltage rate while it moves (the synthetic ramps use it); span/10 s when it holds still.
double ramp_rate_v_per_s(const std::vector<double>& v, std::size_t k, double dt_s, double span_v) {
  double sum = 0;
  std::size_t moving = 0;
  for (std::size_t i = 1; i < k; ++i)
    if (v[i] != v[i - 1]) sum += std::abs(v[i] - v[i - 1]) / dt_s, ++moving;
  return moving ? std::max(sum / static_cast<double>(moving), 1e-3 * span_v) : span_v / 10.0;
}

// Decaying staircases: rested at the far end, to a turning point (half, three quarters or all of the way to the
// range's end), then swings around v0, each `shrink` of the last, until one is under 2 % of the range, held 0 or
// 100 s: the nested memory of several swings (what a real history leaves), which one turning point cannot.
template <class Rows>
void add_staircases(double v0, double lo, double hi, double dt, const Rows& rows, std::size_t max_rows,
                    std::vector<StartHistory>* out) {
  for (int side : {+1, -1}) {
    const double end = side > 0 ? hi : lo;
    if (std::abs(end - v0) < 1e-6 * (hi - lo)) continue;
    for (double f : {0.5, 0.75, 1.0})
      for (double shrink : {0.2, 0.35, 0.5, 0.7, 0.85}) {
        StartHistory h;
        h.rest = false;
        h.reset_v = side > 0 ? lo : hi;
        h.turn_v = v0 + f * (end - v0);
        h.start_v = v0;
        h.dt_s = dt;
        h.ramp_to_turn_rows = rows(h.turn_v - h.reset_v);
        h.shrink = shrink;
        double from = h.turn_v, swing = h.turn_v - v0;
        while (from != v0) {
          swing *= -shrink;
          const double to = std::abs(swing) < 0.02 * (hi - lo) ? v0 : std::clamp(v0 + swing, lo, hi);
          const std::size_t n = rows(to - from);
          for (std::size_t j = 1; j <= n; ++j)
            h.replay_v.push_back(from + (to - from) * static_cast<double>(j) / static_cast<double>(n));
          from = to;
        }
        for (double age_s : {0.0, 100.0}) {
          h.hold_rows = static_cast<std::size_t>(std::lround(age_s / dt));
          if (h.ramp_to_turn_rows + h.replay_v.size() + h.hold_rows > max_rows) break;
          out->push_back(h);
        }
      }
  }
}

// Rest, then from each side's turning points (a quarter to all of the way to the range's end), held for each age
// that fits the synthetic-history budget; then the decaying staircases and the window played backwards (below).
std::vector<StartHistory> candidates(const io::Dataset& data, const std::string& axis, std::size_t k,
                                     const StartOptions& o) {
  const std::vector<double>& v = data.axis(axis).voltage_v;
  const double dt = k > 1 ? (data.time_s[k - 1] - data.time_s[0]) / static_cast<double>(k - 1) : data.sample_period_s();
  double lo = *std::min_element(v.begin(), v.begin() + static_cast<long>(k));
  double hi = *std::max_element(v.begin(), v.begin() + static_cast<long>(k));
  double dmin = lo, dmax = hi;
  for (double x : v)
    if (std::isfinite(x)) dmin = std::min(dmin, x), dmax = std::max(dmax, x);
  const double span = std::max(dmax - dmin, 1e-6);
  lo = std::isfinite(o.voltage_min_v) ? std::min(lo, o.voltage_min_v) : std::min(lo, v[0] - span);
  hi = std::isfinite(o.voltage_max_v) ? std::max(hi, o.voltage_max_v) : std::max(hi, v[0] + span);
  const double v0 = v[0], rate = ramp_rate_v_per_s(v, k, dt, hi - lo);
  auto rows = [&](double dv) { return std::max<std::size_t>(1, static_cast<std::size_t>(std::ceil(std::abs(dv) / rate / dt))); };
  std::vector<StartHistory> out(1);
  out[0].start_v = v0;
  out[0].dt_s = dt;
  for (int side : {+1, -1}) {
    const double end = side > 0 ? hi : lo;
    if (std::abs(end - v0) < 1e-6 * (hi - lo)) continue;
    // Rested long (where the slow creep modes sit) at the far end, at the first voltage (a short excursion), at
    // the turning side's end, or at the range's middle (the stand-in for the mean voltage of operation, near which
    // a slow state sits; skipped where it is the first voltage, as without a training range).
    std::vector<double> rests = {side > 0 ? lo : hi, v0, side > 0 ? hi : lo};
    const double mid = 0.5 * (lo + hi);
    if (o.rest_at_middle && std::abs(mid - v0) >= 1e-6 * (hi - lo)) rests.push_back(mid);
    for (double f : {0.25, 0.5, 0.75, 1.0})
      for (double reset_v : rests) {
        StartHistory h;
        h.rest = false;
        h.reset_v = reset_v;
        h.turn_v = v0 + f * (end - v0);
        h.start_v = v0;
        h.dt_s = dt;
        h.ramp_to_turn_rows = rows(h.turn_v - h.reset_v);
        h.ramp_to_start_rows = rows(h.turn_v - v0);
        for (double age_s : {0.0, 10.0, 100.0, 1000.0}) {
          h.hold_rows = static_cast<std::size_t>(std::lround(age_s / dt));
          if (h.ramp_to_turn_rows + h.ramp_to_start_rows + h.hold_rows > o.max_history_samples) break;
          out.push_back(h);
        }
      }
  }
  if (o.staircases) add_staircases(v0, lo, hi, dt, rows, o.max_history_samples, &out);
  // The window's own motion backwards, from its last voltage to v0, after a rest at either end of the range or at
  // that last voltage: a pre-history with the window's statistics (its turning points, its rate), which the ramps
  // above do not have (a recurrent model's state, small turning points near v0).
  if (o.replay_window && k > 2) {
    for (double reset_v : {lo, hi, v[k - 1]}) {
      StartHistory h;
      h.rest = false;
      h.reset_v = reset_v;
      h.turn_v = v[k - 1];
      h.start_v = v0;
      h.dt_s = dt;
      h.ramp_to_turn_rows = reset_v == v[k - 1] ? 0 : rows(h.turn_v - h.reset_v);
      h.replay_v.assign(v.rend() - static_cast<long>(k) + 1, v.rend());
      for (double age_s : {0.0, 10.0, 100.0, 1000.0}) {
        h.hold_rows = static_cast<std::size_t>(std::lround(age_s / dt));
        if (h.ramp_to_turn_rows + h.replay_v.size() + h.hold_rows > o.max_history_samples) break;
        out.push_back(h);
      }
    }
  }
  return out;
}

// The voltage range the window's sweep is measured against: the given limits (the training range), else the data's
// voltage span over all its rows.
double window_range_v(const io::Dataset& data, const std::string& axis, const StartOptions& o) {
  if (std::isfinite(o.voltage_min_v) && std::isfinite(o.voltage_max_v)) return o.voltage_max_v - o.voltage_min_v;
  double lo = INFINITY, hi = -INFINITY;
  for (double x : data.axis(axis).voltage_v)
    if (std::isfinite(x)) lo = std::min(lo, x), hi = std::max(hi, x);
  return hi > lo ? hi - lo : 0.0;
}

// The candidate's window, free run from its state.
std::vector<double> stream_window(const Model& state, const io::Dataset& window, const std::string& axis) {
  ModelPtr m = state.clone();
  StreamOptions so;
  so.reset = false;
  so.keep_diverging = true;  // a diverging candidate scores badly instead of stopping the search
  return stream_model(*m, window, axis, so).prediction;
}

// A candidate whose window diverged (the stream keeps it finite at ±1e12 nm): no plausible history.
bool diverged(const std::vector<double>& p) {
  return std::any_of(p.begin(), p.end(), [](double x) { return !(std::abs(x) < 1e11); });
}

// Per entry i < n, the range of values[c][i] over the plausible candidates c (those whose window `preds[c]` did not
// diverge): how far the unknown history can move it; 0 where no candidate is plausible.
std::vector<double> candidate_range(const std::vector<std::vector<double>>& values,
                                    const std::vector<std::vector<double>>& preds, std::size_t n) {
  std::vector<double> lo(n, INFINITY), hi(n, -INFINITY), r(n, 0.0);
  for (std::size_t c = 0; c < preds.size(); ++c) {
    if (diverged(preds[c])) continue;
    for (std::size_t i = 0; i < n; ++i) lo[i] = std::min(lo[i], values[c][i]), hi[i] = std::max(hi[i], values[c][i]);
  }
  for (std::size_t i = 0; i < n; ++i) r[i] = hi[i] >= lo[i] && std::isfinite(hi[i] - lo[i]) ? hi[i] - lo[i] : 0.0;
  return r;
}

// Per row, how far apart the candidates' predictions are: what the unknown history can still change there.
std::vector<double> state_spread(const std::vector<std::vector<double>>& preds, std::size_t k) {
  return candidate_range(preds, preds, k);
}

// The reading noise: the scatter of the residual's steps (the model follows the motion; a slow state error barely
// moves from one row to the next).
double step_noise(const double* y, const double* p, std::size_t n) {
  double ss = 0;
  for (std::size_t i = 1; i < n; ++i) {
    const double d = (y[i] - p[i]) - (y[i - 1] - p[i - 1]);
    ss += d * d;
  }
  return n > 1 ? std::sqrt(ss / static_cast<double>(n - 1) / 2.0) : 0.0;
}

// Offset weighted by 1/(noise² + (spread/2)²): rows where the history still matters count little. Its σ: the
// weighted spread (one unknown state shifts every row alike, it does not average out) and the noise's share.
struct Weighted {
  double offset_nm = 0, sigma_nm = 0, rms_nm = 0, n_eff = 1;
};
Weighted weighted_offset(const double* y, const double* p, const std::vector<double>& w,
                         const std::vector<double>& spread, double noise_nm) {
  const std::size_t n = w.size();
  double sw = 0, sw2 = 0, swr = 0, sws = 0;
  for (std::size_t i = 0; i < n; ++i) sw += w[i], sw2 += w[i] * w[i], swr += w[i] * (y[i] - p[i]), sws += w[i] * spread[i];
  Weighted f;
  f.offset_nm = swr / sw;
  double ss = 0, lag = 0, prev = 0, plain = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const double r = y[i] - p[i] - f.offset_nm;
    ss += w[i] * r * r;
    plain += r * r;
    if (i) lag += r * prev;
    prev = r;
  }
  f.rms_nm = std::sqrt(ss / sw);
  // Kish's effective count of the weights, less the residuals' lag-1 correlation.
  const double rho = plain > 0 ? std::clamp(lag / plain, 0.0, 0.99) : 0.0;
  f.n_eff = std::max(1.0, sw * sw / sw2 * (1 - rho) / (1 + rho));
  const double state = 0.5 * sws / sw, noise = std::max(f.rms_nm, noise_nm) / std::sqrt(f.n_eff);
  f.sigma_nm = std::sqrt(state * state + noise * noise);
  return f;
}

}  // namespace

std::string StartHistory::describe() const {
  if (rest) return "rest at " + fmt(start_v, 4) + " V";
  if (shrink > 0)
    return "rested at " + fmt(reset_v, 4) + " V, from " + fmt(turn_v, 4) + " V in swings around " + fmt(start_v, 4) +
           " V shrinking by " + fmt(shrink, 3) + ", held " + fmt(static_cast<double>(hold_rows) * dt_s, 4) + " s";
  if (!replay_v.empty())
    return "rested at " + fmt(reset_v, 4) + " V, the window backwards from " + fmt(turn_v, 4) + " V to " +
           fmt(start_v, 4) + " V, held " + fmt(static_cast<double>(hold_rows) * dt_s, 4) + " s";
  return "rested at " + fmt(reset_v, 4) + " V, from " + fmt(turn_v, 4) + " V " + (turn_v > start_v ? "down" : "up") +
         " to " + fmt(start_v, 4) + " V, held " + fmt(static_cast<double>(hold_rows) * dt_s, 4) + " s";
}

std::string StartEstimate::describe() const {
  std::ostringstream s;
  s.precision(4);
  s << "start estimate over " << window_rows << " rows: " << candidate << " (best of " << candidates
    << ")";
  if (linear_states)
    s << ", " << linear_states << " creep states fitted (largest shift " << linear_shift_max_nm << " nm)";
  s << ", offset " << offset_nm << " +- " << offset_sigma_nm << " nm, window RMS " << rms_rest_nm
    << " nm offset-only -> " << rms_nm << " nm";  // ASCII: rosconsole logs do not keep UTF-8
  if (range_v > 0) {
    s << "; the window swept " << std::lround(100.0 * swept_fraction()) << " % of the " << range_v << " V range";
    if (swept_fraction() < kWindowSweepAdvised)
      s << " (the memory of wider swings is not in it: a longer window that sweeps the range starts better)";
  }
  return s.str();
}

WindowFit window_offset(const double* measured_nm, const double* predicted_nm, std::size_t n) {
  WindowFit f;
  double mean = 0;
  for (std::size_t i = 0; i < n; ++i) mean += measured_nm[i] - predicted_nm[i];
  mean = n ? mean / static_cast<double>(n) : 0.0;
  double ss = 0, lag = 0, prev = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const double r = measured_nm[i] - predicted_nm[i] - mean;
    ss += r * r;
    if (i) lag += r * prev;
    prev = r;
  }
  f.offset_nm = mean;
  f.rms_nm = n ? std::sqrt(ss / static_cast<double>(n)) : 0.0;
  f.n_eff = static_cast<double>(std::max<std::size_t>(n, 1));
  if (n < 2) {
    f.sigma_nm = std::numeric_limits<double>::quiet_NaN();
    return f;
  }
  // Correlated residuals average less.
  const double rho = ss > 0 ? std::clamp(lag / ss, 0.0, 0.99) : 0.0;
  f.n_eff = std::max(1.0, static_cast<double>(n) * (1 - rho) / (1 + rho));
  f.sigma_nm = std::sqrt(ss / static_cast<double>(n - 1) / f.n_eff);
  return f;
}

void prepare_start(Model& model, const io::Dataset& data, const std::string& axis, const StartHistory& h) {
  const io::AxisSeries& ax = data.axis(axis);
  InputResolver inputs(data, model.aux_inputs(), axis);
  std::vector<double> aux(inputs.size());
  if (!aux.empty()) inputs.fill(0, aux.data());
  const double* a = aux.empty() ? nullptr : aux.data();
  if (h.rest) {
    model.reset(ax.voltage_v[0], ax.position_nm[0]);
  } else {
    model.reset(h.reset_v, ax.position_nm[0]);
    run_rows(model, h.reset_v, h.turn_v, h.ramp_to_turn_rows, a);
    for (double x : h.replay_v) run_rows(model, x, x, 1, a);
    run_rows(model, h.turn_v, h.start_v, h.replay_v.empty() ? h.ramp_to_start_rows : 0, a);
    run_rows(model, h.start_v, h.start_v, h.hold_rows, a);
  }
  const std::size_t n = std::min(h.linear_shift_nm.size(), model.linear_state_count());
  for (std::size_t k = 0; k < n; ++k) model.shift_linear_state(k, h.linear_shift_nm[k]);
}

std::size_t start_window_rows(const io::Dataset& data, const std::string& axis, double window_s) {
  if (!(window_s > 0) || !std::isfinite(window_s))
    throw std::invalid_argument("start window must be a finite time > 0 s (got " + fmt(window_s, 6) + ")");
  if (data.empty()) throw io::DataError(data.source_or_data() + ": no rows for the start window");
  const std::size_t k = window_rows(data, window_s);
  check_window(data, axis, window_s, k);
  return k;
}

namespace {
// Every candidate's window predictions (candidates sharing a turning point differ only in the hold: the last one's
// state is continued instead of rebuilt).
// states[c][k]: candidate c's linear state k at the window's start.
std::vector<std::vector<double>> candidate_windows(const Model& model, const io::Dataset& data, const std::string& axis,
                                                   const std::vector<StartHistory>& cands, const io::Dataset& window,
                                                   std::vector<std::vector<double>>* states) {
  std::vector<std::vector<double>> out;
  ModelPtr m = model.clone();
  const StartHistory* prev = nullptr;
  std::vector<double> a(m->aux_inputs().size());
  if (!a.empty()) InputResolver(data, m->aux_inputs(), axis).fill(0, a.data());
  for (const StartHistory& h : cands) {
    const bool same_path = prev && !prev->rest && !h.rest && prev->turn_v == h.turn_v && prev->reset_v == h.reset_v &&
                           prev->replay_v == h.replay_v && h.hold_rows >= prev->hold_rows;
    if (same_path)
      run_rows(*m, h.start_v, h.start_v, h.hold_rows - prev->hold_rows, a.empty() ? nullptr : a.data());
    else
      prepare_start(*m, data, axis, h);
    prev = &h;
    states->emplace_back(m->linear_state_count());
    for (std::size_t k = 0; k < states->back().size(); ++k) states->back()[k] = m->linear_state_nm(k);
    out.push_back(stream_window(*m, window, axis));
  }
  return out;
}

// The search (the header): weights from the candidates' spread, each candidate's weighted offset fit, then among the
// fits as good as the best within the margin the one that needs the least offset.
StartEstimate choose_start(const std::vector<std::vector<double>>& preds, const double* y, std::size_t k,
                           std::size_t* chosen, std::vector<double>* weights) {
  const std::vector<double> spread = state_spread(preds, k);
  const double noise = std::max(step_noise(y, preds[0].data(), k), 1e-9);
  std::vector<double> w(k);
  for (std::size_t i = 0; i < k; ++i) w[i] = 1.0 / (noise * noise + 0.25 * spread[i] * spread[i]);
  std::vector<Weighted> fits;
  for (const auto& p : preds) fits.push_back(weighted_offset(y, p.data(), w, spread, noise));
  std::size_t best = 0;
  for (std::size_t c = 1; c < fits.size(); ++c)
    if (fits[c].rms_nm < fits[best].rms_nm) best = c;
  const double n_eff = fits[0].n_eff, margin = kStartMargin * std::log(n_eff);
  std::size_t pick = best;
  for (std::size_t c = 0; c < fits.size(); ++c)
    if (n_eff * 2 * std::log(fits[c].rms_nm / fits[best].rms_nm) <= margin &&
        std::abs(fits[c].offset_nm) < std::abs(fits[pick].offset_nm))
      pick = c;
  StartEstimate e;
  e.offset_nm = fits[pick].offset_nm;
  e.offset_sigma_nm = fits[pick].sigma_nm;
  e.rms_nm = fits[pick].rms_nm;
  e.rms_best_nm = fits[best].rms_nm;
  e.rms_rest_nm = fits[0].rms_nm;
  e.spread_end_nm = spread[k - 1];
  *chosen = pick;
  *weights = std::move(w);
  return e;
}

// Each linear state's prior at the window's start, as a scale s_j [nm] and a mean m_j [in s_j] relative to the
// chosen candidate's state: the model's learned ModelMeta::state_prior at the first voltage (where training-like
// operation keeps the state, and its scatter there) when the file has one for every state; otherwise half the
// state's range over the plausible candidates (how far a history can put it), centred on the candidate.
void state_prior(const Model& model, double v0, const std::vector<std::vector<double>>& preds,
                 const std::vector<std::vector<double>>& states, std::size_t chosen, std::vector<double>* scale,
                 std::vector<double>* mean) {
  const std::size_t n = states[chosen].size();
  mean->assign(n, 0.0);
  const std::vector<LinearStatePrior>& learned = model.meta.state_prior;
  if (learned.size() != n) {
    *scale = candidate_range(states, preds, n);
    for (double& x : *scale) x *= 0.5;
    return;
  }
  scale->assign(n, 0.0);
  for (std::size_t j = 0; j < n; ++j) {
    // A state training kept exactly on its line (no scatter) is still moved there: a scale of 1 pm, not 0 (unfitted).
    (*scale)[j] = std::max(learned[j].sigma_nm, 1e-3);
    (*mean)[j] = (learned[j].intercept_nm + learned[j].slope_nm_per_v * v0 - states[chosen][j]) / (*scale)[j];
  }
}

// The linear states' responses over the window (the header): φ_j, the window's response to a shift of state j by
// its prior scale s_j (state_prior), streamed from `history` = candidate `chosen` (exact for linear states, and the
// same from every state) less that candidate's own window preds[chosen].
struct StateBasis {
  // States with a prior scale > 1e-6 nm (without a learned prior, a state every candidate puts at one place is not
  // fitted).
  std::vector<std::size_t> used;
  std::vector<double> prior;      // s_j of every state
  std::vector<double> mean;       // m_j of every state, in units of s_j
  std::vector<std::vector<double>> phi;
};
StateBasis state_basis(const Model& model, const io::Dataset& data, const std::string& axis, const io::Dataset& window,
                       const std::vector<std::vector<double>>& preds, const std::vector<std::vector<double>>& states,
                       std::size_t chosen, const StartHistory& history) {
  StateBasis out;
  const std::size_t n_states = states.empty() ? 0 : states[0].size();
  if (n_states == 0) return out;
  state_prior(model, data.axis(axis).voltage_v[0], preds, states, chosen, &out.prior, &out.mean);
  ModelPtr base = model.clone();
  prepare_start(*base, data, axis, history);
  const std::vector<double>& p = preds[chosen];  // the window from `history`, streamed by candidate_windows
  for (std::size_t j = 0; j < n_states; ++j) {
    if (!(out.prior[j] > 1e-6)) continue;
    ModelPtr m = base->clone();
    m->shift_linear_state(j, out.prior[j]);
    std::vector<double> r = stream_window(*m, window, axis);
    for (std::size_t i = 0; i < r.size(); ++i) r[i] -= p[i];
    out.used.push_back(j);
    out.phi.push_back(std::move(r));
  }
  return out;
}

// One candidate's fit with its linear states: measured − predicted ≈ c + Σ_j δ_j φ_j with the row weights w, the
// priors δ_j ~ N(m_j, 1) (in units of s_j) and c ~ N(0, noise²); the posterior mean (a ridge solve of 1 + states unknowns).
struct StateFit {
  double offset_nm = 0, sigma_nm = 0, rms_nm = 0;
  std::vector<double> shift_nm;  // per state (0 for those not fitted)
  bool ok = false;
};
StateFit solve_states(const StateBasis& basis, const double* y, const std::vector<double>& p,
                      const std::vector<double>& w, double noise_nm) {
  using Eigen::Index;
  StateFit f;
  const std::size_t k = w.size(), n_used = basis.used.size();
  const Index q = static_cast<Index>(n_used) + 1;  // unknowns: the offset [nm], each used state [its prior]
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(q, q);
  Eigen::VectorXd b = Eigen::VectorXd::Zero(q), row(q);
  for (std::size_t i = 0; i < k; ++i) {
    row[0] = 1.0;
    for (std::size_t j = 0; j < n_used; ++j) row[static_cast<Index>(j + 1)] = basis.phi[j][i];
    a.selfadjointView<Eigen::Lower>().rankUpdate(row, w[i]);
    b += w[i] * (y[i] - p[i]) * row;
  }
  a = a.selfadjointView<Eigen::Lower>();
  a(0, 0) += 1.0 / (noise_nm * noise_nm);
  for (Index j = 1; j < q; ++j) a(j, j) += 1.0, b[j] += basis.mean[basis.used[static_cast<std::size_t>(j - 1)]];
  const Eigen::LDLT<Eigen::MatrixXd> ldlt(a);
  const Eigen::VectorXd theta = ldlt.solve(b);
  if (!theta.allFinite()) return f;
  double ss = 0, sw = 0, sw2 = 0, plain = 0, lag = 0, prev = 0;
  for (std::size_t i = 0; i < k; ++i) {
    double r = y[i] - p[i] - theta[0];
    for (std::size_t j = 0; j < n_used; ++j) r -= theta[static_cast<Index>(j + 1)] * basis.phi[j][i];
    ss += w[i] * r * r, sw += w[i], sw2 += w[i] * w[i], plain += r * r;
    if (i) lag += r * prev;
    prev = r;
  }
  // The 1σ the estimator starts from: the posterior σ of the fitted correction at the window's last row (offset and
  // states together), the rows counted as n_eff (the residuals' correlation) of k.
  const double rho = plain > 0 ? std::clamp(lag / plain, 0.0, 0.99) : 0.0;
  const double n_eff = std::max(1.0, sw * sw / sw2 * (1 - rho) / (1 + rho));
  row[0] = 1.0;
  for (std::size_t j = 0; j < n_used; ++j) row[static_cast<Index>(j + 1)] = basis.phi[j][k - 1];
  const double var_end = row.dot(ldlt.solve(row)) * static_cast<double>(k) / n_eff;
  f.shift_nm.assign(basis.prior.size(), 0.0);
  for (std::size_t j = 0; j < n_used; ++j)
    f.shift_nm[basis.used[j]] = theta[static_cast<Index>(j + 1)] * basis.prior[basis.used[j]];
  f.offset_nm = theta[0];
  f.sigma_nm = std::sqrt(std::max(var_end, 0.0));
  f.rms_nm = std::sqrt(ss / sw);
  f.ok = true;
  return f;
}

void apply_state_fit(const StateFit& f, const StateBasis& basis, StartEstimate* e) {
  e->history.linear_shift_nm = f.shift_nm;
  e->linear_states = basis.used.size();
  e->linear_shift_max_nm = 0;
  for (double d : f.shift_nm) e->linear_shift_max_nm = std::max(e->linear_shift_max_nm, std::abs(d));
  e->offset_nm = f.offset_nm;
  e->offset_sigma_nm = f.sigma_nm;
  e->rms_nm = f.rms_nm;
}

// The chosen candidate's linear states fitted on the window (StartOptions::fit_linear_states); the candidate itself
// is chosen by choose_start, without the states (docs/models.md, "The stage matrix").
void fit_linear_states(const Model& model, const io::Dataset& data, const std::string& axis, const io::Dataset& window,
                       const std::vector<StartHistory>& cands, const std::vector<std::vector<double>>& preds,
                       const std::vector<std::vector<double>>& states, std::size_t chosen,
                       const std::vector<double>& w, StartEstimate* e) {
  const StateBasis basis = state_basis(model, data, axis, window, preds, states, chosen, cands[chosen]);
  if (basis.used.empty()) return;
  const double* y = data.axis(axis).position_nm.data();
  const double noise = std::max(step_noise(y, preds[chosen].data(), w.size()), 1e-9);
  const StateFit f = solve_states(basis, y, preds[chosen], w, noise);
  if (f.ok) apply_state_fit(f, basis, e);
}
}  // namespace

StartEstimate estimate_start(const Model& model, const io::Dataset& data, const std::string& axis,
                             const StartOptions& o) {
  const std::size_t k = start_window_rows(data, axis, o.window_s);
  const io::Dataset window = data.slice(0, k);
  const double* y = data.axis(axis).position_nm.data();
  StartOptions range = o;  // unset limits: the training data's voltage range, where the model has seen the stage
  if (!std::isfinite(range.voltage_min_v)) range.voltage_min_v = model.meta.train_voltage_min_v;
  if (!std::isfinite(range.voltage_max_v)) range.voltage_max_v = model.meta.train_voltage_max_v;
  std::vector<StartHistory> cands = candidates(data, axis, k, range);
  if (!o.search_history) cands.resize(1);
  std::vector<std::vector<double>> states;
  const std::vector<std::vector<double>> preds = candidate_windows(model, data, axis, cands, window, &states);
  StartEstimate e;
  if (o.search_history) {
    std::size_t chosen = 0;
    std::vector<double> w;
    e = choose_start(preds, y, k, &chosen, &w);
    e.history = cands[chosen];
    if (o.fit_linear_states) fit_linear_states(model, data, axis, window, cands, preds, states, chosen, w, &e);
    e.window_weight = std::move(w);
  } else {  // offset only: rest, the plain mean over the window
    const WindowFit f = window_offset(y, preds[0].data(), k);
    e.history = cands[0];
    e.offset_nm = f.offset_nm;
    e.offset_sigma_nm = f.sigma_nm;
    e.rms_nm = e.rms_best_nm = e.rms_rest_nm = f.rms_nm;
  }
  e.candidates = cands.size();
  e.window_rows = k;
  const auto& v = data.axis(axis).voltage_v;
  const auto [lo, hi] = std::minmax_element(v.begin(), v.begin() + static_cast<long>(k));
  e.window_swept_v = *hi - *lo;
  e.range_v = window_range_v(data, axis, range);
  e.candidate = e.history.describe();
  return e;
}

std::vector<LinearStatePrior> learn_state_prior(const Model& model, const io::Dataset& train, const std::string& axis) {
  if (train.empty()) return {};
  const std::size_t n = model.linear_state_count();
  if (n == 0) return {};
  const std::vector<double>& v = train.axis(axis).voltage_v;
  double v_lo = INFINITY, v_hi = -INFINITY, v_sum = 0, v_n = 0;
  for (double x : v)
    if (std::isfinite(x)) v_lo = std::min(v_lo, x), v_hi = std::max(v_hi, x), v_sum += x, ++v_n;
  if (!(v_hi >= v_lo)) return {};
  // Warm-up passes over the data from a rest at its mean voltage (it continues into the measured pass) and at either
  // end of its range: how far apart the two ends leave each state is what one training length cannot tell about it
  // (a mode much slower than the recording keeps its start), and widens its prior.
  StreamOptions so;
  so.keep_diverging = true;
  so.reset = false;
  const double y0 = train.axis(axis).position_nm[0];
  ModelPtr m = model.clone(), lo = model.clone(), hi = model.clone();
  m->reset(v_sum / v_n, y0);
  lo->reset(v_lo, y0);
  hi->reset(v_hi, y0);
  for (Model* w : {m.get(), lo.get(), hi.get()}) stream_model(*w, train, axis, so);
  std::vector<double> unsettled(n);
  for (std::size_t k = 0; k < n; ++k) unsettled[k] = std::abs(lo->linear_state_nm(k) - hi->linear_state_nm(k));
  // Sums for the per-state least-squares lines, kept about the first row's values (shifted sums: exact in a long
  // run at constant memory, whatever the length of the training data).
  double v_ref = NAN, cnt = 0, sv = 0, svv = 0;
  std::vector<double> x_ref(n), sx(n, 0.0), sxx(n, 0.0), svx(n, 0.0);
  so.after_row = [&](std::size_t i, const Model& mm) {
    if (!std::isfinite(v[i])) return;  // (a non-finite voltage leaves the states non-finite: no prior, below)
    if (std::isnan(v_ref)) {
      v_ref = v[i];
      for (std::size_t k = 0; k < n; ++k) x_ref[k] = mm.linear_state_nm(k);
    }
    const double dv = v[i] - v_ref;
    cnt += 1, sv += dv, svv += dv * dv;
    for (std::size_t k = 0; k < n; ++k) {
      const double dx = mm.linear_state_nm(k) - x_ref[k];
      sx[k] += dx, sxx[k] += dx * dx, svx[k] += dv * dx;
    }
  };
  stream_model(*m, train, axis, so);
  if (cnt == 0) return {};
  const double mv = sv / cnt, var_v = std::max(svv / cnt - mv * mv, 0.0);
  std::vector<LinearStatePrior> out(n);
  for (std::size_t k = 0; k < n; ++k) {
    const double mx = sx[k] / cnt, var_x = std::max(sxx[k] / cnt - mx * mx, 0.0), cov = svx[k] / cnt - mv * mx;
    const double slope = var_v > 0 ? cov / var_v : 0.0;
    // The scatter about the line (its residual variance var_x − slope·cov, ≥ 0 up to rounding) and half the gap the
    // two warm-ups left.
    const double scatter2 = std::max(var_x - slope * cov, 0.0), half_gap = 0.5 * unsettled[k];
    out[k] = {x_ref[k] + mx - slope * (v_ref + mv), slope, std::sqrt(scatter2 + half_gap * half_gap)};
    if (!std::isfinite(out[k].intercept_nm) || !std::isfinite(out[k].slope_nm_per_v) || !std::isfinite(out[k].sigma_nm))
      return {};  // a diverging or non-finite run: no prior (the model file could not hold it)
  }
  return out;
}

}  // namespace piezo::models
