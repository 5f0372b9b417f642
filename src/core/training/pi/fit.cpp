// The fit of kinds "pi", "pi_creep_*" and the preisach kinds: the choices made on the data (play count, input map,
// creep input, hold weight) by free-run validation error, the creep-law searches and the alternations on H.
#include <algorithm>
#include <cmath>
#include <functional>
#include <stdexcept>

#include "basis.h"
#include "evaluate.h"
#include "gram.h"
#include "options.h"
#include "piezo_compensation/io/dataset.h"
#include "piezo_compensation/io/holds.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/training/fitters.h"

namespace piezo::training {

using namespace models;  // the fit code names the model's classes as models/ does

namespace pi {
namespace {

// Golden-section minimisation of f on [lo, hi].
template <class F>
double golden(F&& f, double lo, double hi, int iters) {
  const double g = (std::sqrt(5.0) - 1) / 2;
  double x1 = hi - g * (hi - lo), x2 = lo + g * (hi - lo);
  double f1 = f(x1), f2 = f(x2);
  for (int i = 0; i < iters; ++i) {
    if (f1 < f2) {
      hi = x2, x2 = x1, f2 = f1;
      x1 = hi - g * (hi - lo);
      f1 = f(x1);
    } else {
      lo = x1, x1 = x2, f1 = f2;
      x2 = lo + g * (hi - lo);
      f2 = f(x2);
    }
  }
  return f1 < f2 ? x1 : x2;
}

// Grid then golden refinement of a 1-D parameter.
template <class F>
double search_1d(F&& f, double lo, double hi, int grid, int iters) {
  double best = lo, best_f = INFINITY;
  const double step = (hi - lo) / (grid - 1);
  for (int i = 0; i < grid; ++i) {
    const double x = lo + step * i;
    const double v = f(x);
    if (v < best_f) best_f = v, best = x;
  }
  return golden(f, std::max(lo, best - step), std::min(hi, best + step), iters);
}

// Hold rows of the training or validation data (the hold weights, the validation's hold and walk errors): the
// phase markers where present, else runs of a constant voltage lasting at least 2 s and 20 samples, within 1e-4 of
// the voltage span (a read-back with a few LSB of noise still counts), without the row that steps onto it.
std::vector<char> fit_hold_rows(const io::Dataset& data, const std::string& axis) {
  io::HoldRule rule;
  rule.min_duration_s = 2.0;
  rule.min_rows = 20;
  rule.tolerance_v = 0.0;
  rule.tolerance_of_span = 1e-4;
  rule.skip_first_row = true;
  return io::hold_rows(data.size(), io::find_holds(data, axis, rule));
}

struct Score {
  double all = INFINITY, hold = NAN, walk = NAN;
};

// Free-run MAE against the measurement on the validation data, split into hold and walk samples: the model streamed
// (models::stream_model) over the training data first, as the validation data continue it in time (its warm-up; a
// validation set of several recordings: the training data, then each validation recording, the first continuing).
// A diverging prediction scores infinite. abs_err (optional): the per-sample absolute errors.
Score validation_score(const PiCreepModel& fitted, const FitRequest& req, const std::vector<char>& val_hold,
                       std::vector<double>* abs_err = nullptr) {
  PiCreepModel m = fitted;
  const io::Dataset& val = *req.validation;
  StreamOptions so;
  so.keep_diverging = true;
  if (val.recording_count() > 1) {
    stream_model(m, *req.train, req.axis, so);
    so.reset = false;
  } else {
    so.warmup = req.train;
  }
  const std::vector<double> pred = stream_model(m, val, req.axis, so).prediction;
  const std::vector<double>& y = val.axis(req.axis).position_nm;
  double s[2] = {0, 0};
  std::size_t n[2] = {0, 0};
  for (std::size_t t = 0; t < pred.size(); ++t) {
    const double e = std::abs(pred[t]) >= 1e12 ? INFINITY : std::abs(pred[t] - y[t]);  // kept finite: diverged
    if (abs_err) abs_err->push_back(e);
    const int k = val_hold[t] ? 1 : 0;
    s[k] += e, ++n[k];
  }
  Score sc;
  sc.all = (n[0] + n[1]) ? (s[0] + s[1]) / double(n[0] + n[1]) : INFINITY;
  if (!std::isfinite(sc.all)) sc.all = INFINITY;
  if (n[1]) sc.hold = s[1] / n[1];
  if (n[0]) sc.walk = s[0] / n[0];
  return sc;
}

const io::AxisSeries& training_axis(const FitRequest& req) {
  if (!req.train) throw std::runtime_error("PI fit: no training data");
  const io::AxisSeries& ax = req.train->axis(req.axis);
  if (ax.voltage_v.size() < 10) throw std::runtime_error("PI fit: need at least 10 samples");
  return ax;
}

const io::AxisSeries* validation_axis(const FitRequest& req) {
  if (req.validation && req.validation->has_axis(req.axis) && req.validation->axis(req.axis).voltage_v.size() >= 10)
    return &req.validation->axis(req.axis);
  return nullptr;
}

// Smallest allowed initial slope: a fraction of the overall voltage→position slope (0 when that is not positive).
double min_slope(const io::AxisSeries& ax, double fraction) {
  double mv = 0, my = 0;
  const std::size_t N = ax.voltage_v.size();
  for (std::size_t t = 0; t < N; ++t) mv += ax.voltage_v[t], my += ax.position_nm[t];
  mv /= N, my /= N;
  double cvy = 0, cvv = 0;
  for (std::size_t t = 0; t < N; ++t) {
    cvy += (ax.voltage_v[t] - mv) * (ax.position_nm[t] - my);
    cvv += (ax.voltage_v[t] - mv) * (ax.voltage_v[t] - mv);
  }
  return cvv > 0 && cvy > 0 ? fraction * cvy / cvv : 0.0;
}

using SseFn = std::function<double(const CreepParams&)>;

// Where a creep-on-H alternation stopped (after `done` rounds, on the training data with sample weights `weight`): a
// later fit of the same data and weights with more rounds continues from here, with the same result as starting
// over (each round depends only on the creep law and the play weights the last one left).
struct Alternation {
  CreepParams cp;
  EvalResult best;
  int done = 0;
  const std::vector<double>* weight = nullptr;
};

// One fit_pi_creep call: the data, the options and the choices made on them, each choice a member.
class PiCreepFit {
 public:
  PiCreepFit(const FitRequest& req, CreepKind kind, bool preisach);
  models::ModelPtr run();

 private:
  double clamp_tau(double t) const { return std::min(tau_hi_, std::max(tau_lo_, t)); }
  // Keeps the log law's slowest mode inside the data for a given t1.
  int log_decades(double t1) const {
    return std::max(1, std::min(cp0_.decades, static_cast<int>(std::floor(std::log10(tau_hi_ / t1) + 1e-9))));
  }
  void report(const char* what) {
    ++evals_;
    if (req_.progress) req_.progress(std::min<double>(evals_, total_), total_, what);
  }
  CreepParams initial_creep() const;
  Basis basis_n(std::vector<double> thresholds, bool input_map = false) const;
  // One fit for given thresholds, creep input, sample weights and alternations. `alt` (training data only): where
  // its alternation stopped, and where it continues from when it stopped earlier with the same weights.
  std::unique_ptr<PiCreepModel> fit_with(const FitData& d, const Basis& r, bool on_h, int alternations,
                                         const std::vector<double>* weight,
                                         std::unique_ptr<PiCreepModel>* v_model = nullptr,
                                         Alternation* alt = nullptr);
  EvalResult iterate_joint_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best);
  EvalResult alternate_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters);
  EvalResult continue_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters);
  void search_creep_law(CreepParams& cp, const SseFn& sse_fn, bool refine_only);
  void search_log_t1(CreepParams& cp, const SseFn& sse_of, bool refine_only) const;
  void search_alpha(CreepParams& cp, const SseFn& sse_of, bool refine_only) const;
  void search_lti_taus(CreepParams& cp, const SseFn& sse_of, bool refine_only) const;
  // The choices, in the order run() makes them.
  Basis choose_play_count();
  std::unique_ptr<PiCreepModel> choose_creep_input(const Basis& r, Score& score);
  double choose_hold_weight(const Basis& r, const Score& score, const std::vector<char>& train_hold,
                            std::unique_ptr<PiCreepModel>& m, std::vector<double>& weight);
  void final_fit(const Basis& r, double used_factor, const std::vector<double>& weight,
                 const std::vector<char>& train_hold, std::unique_ptr<PiCreepModel>& m);

  const FitRequest& req_;
  const CreepKind kind_;
  const bool preisach_;
  const io::AxisSeries& ax_;
  const io::AxisSeries* val_;
  const double rate_;
  // What the data can identify: no mode faster than two samples, none slower than the recording.
  const double tau_lo_, tau_hi_;
  const PiFitOptions opt_;
  const CreepParams cp0_;
  FitData d_;
  std::vector<char> val_hold_;
  double min_w0_ = 0;
  int evals_ = 0;
  double total_ = 1;
  // The alternations of the unweighted and the hold-weighted fit, continued by final_fit.
  Alternation alt_plain_, alt_weighted_;
};

PiCreepFit::PiCreepFit(const FitRequest& req, CreepKind kind, bool preisach)
    : req_(req),
      kind_(kind),
      preisach_(preisach),
      ax_(training_axis(req)),
      val_(validation_axis(req)),
      rate_(req.train->sample_rate_hz()),
      tau_lo_(2.0 / rate_),
      tau_hi_(std::max(2.0 * tau_lo_, ax_.voltage_v.size() / rate_)),
      opt_(parse_pi_options(req.options, kind, preisach, val_ != nullptr, tau_lo_, tau_hi_)),
      cp0_(initial_creep()),
      d_{&ax_.voltage_v, &ax_.position_nm, rate_} {
  d_.initial_state_terms = opt_.initial_state_terms;
  if (val_) val_hold_ = fit_hold_rows(*req.validation, req.axis);
  min_w0_ = min_slope(ax_, opt_.min_slope_fraction);
  const double per_search = kind == CreepKind::kNone || kind == CreepKind::kProny ? 1
                            : kind == CreepKind::kLti                           ? 21.0 * opt_.n_pairs
                                                                                : 17;
  total_ = (per_search * 3 + 6 * (per_search + 2)) * (val_ ? 2 : 1) + (preisach ? 8 : 15);
}

CreepParams PiCreepFit::initial_creep() const {
  CreepParams cp0;
  cp0.kind = kind_;
  cp0.decades = opt_.decades;
  cp0.modes_per_decade = opt_.modes_per_decade;
  cp0.tau_min_s = clamp_tau(opt_.tau_min_s);
  cp0.tau_max_s = clamp_tau(opt_.tau_max_s);
  if (kind_ == CreepKind::kFractional && !(cp0.tau_max_s > cp0.tau_min_s)) cp0.tau_min_s = tau_lo_;
  if (kind_ == CreepKind::kProny && cp0.modes_per_decade >= 1 && cp0.tau_max_s > cp0.tau_min_s) {
    // The grid's last mode on or below tau_max_s (log_tau_grid rounds the decade count: 3 per decade on 8 h of
    // data put a mode at 39 000 s).
    const double steps = std::floor(std::log10(cp0.tau_max_s / cp0.tau_min_s) * cp0.modes_per_decade + 1e-9);
    cp0.tau_max_s = cp0.tau_min_s * std::pow(10.0, steps / cp0.modes_per_decade);
  }
  if (kind_ == CreepKind::kLog) {
    cp0.t1_s = clamp_tau(opt_.t1_s);
    cp0.decades = std::max(1, std::min(cp0.decades, static_cast<int>(std::floor(std::log10(tau_hi_ / tau_lo_)))));
  }
  if (kind_ == CreepKind::kFractional && opt_.alpha_given) cp0.alpha = opt_.alpha;
  if (kind_ == CreepKind::kLti) {
    // Given time constants, else spread evenly in log over the identifiable range.
    const double lo = std::log10(tau_lo_), hi = std::log10(tau_hi_);
    if (opt_.taus_given)
      for (double t : opt_.taus_s) cp0.taus_s.push_back(clamp_tau(t));
    else
      for (int j = 0; j < opt_.n_pairs; ++j) cp0.taus_s.push_back(std::pow(10.0, lo + (hi - lo) * (j + 0.5) / opt_.n_pairs));
    cp0.gains_nm_per_v.assign(cp0.taus_s.size(), 0.0);
  }
  cp0.check_sizes();
  return cp0;
}

Basis PiCreepFit::basis_n(std::vector<double> thresholds, bool input_map) const {
  const int n = static_cast<int>(thresholds.size());
  Basis b = basis_for(ax_.voltage_v, std::move(thresholds), preisach_,
                      opt_.knots_per_span > 0 ? opt_.knots_per_span : std::min(n, 12), input_map && !preisach_);
  b.smoothing = opt_.piece_smoothing;
  return b;
}

// With on_h, the voltage-input model it starts from is handed out through v_model (auto input costs nothing extra).
std::unique_ptr<PiCreepModel> PiCreepFit::fit_with(const FitData& d, const Basis& r, bool on_h, int alternations,
                                                   const std::vector<double>* weight,
                                                   std::unique_ptr<PiCreepModel>* v_model, Alternation* alt) {
  FitData dd = d;
  dd.weight = weight;
  const int iters = kind_ == CreepKind::kNone || !on_h ? 0 : alternations;
  const bool joint = kind_ == CreepKind::kProny && opt_.joint_on_h;
  if (alt && !v_model && !joint && alt->done > 0 && alt->done <= iters && alt->weight == weight) {
    CreepParams cp = alt->cp;
    EvalResult best = continue_on_h(dd, r, cp, alt->best, iters - alt->done);
    *alt = Alternation{cp, best, iters, weight};
    return r.model(best.w, best.b, cp, rate_);
  }
  CreepParams cp = cp0_;
  // Creep on the voltage: weights and creep coefficients are jointly linear.
  StaticGram pieces{r.pieces(), {}};
  ModeSearchRows kept;
  search_creep_law(cp, [&](const CreepParams& c) { return evaluate(dd, r, c, min_w0_, &pieces, &kept).sse; }, false);
  EvalResult best = evaluate(dd, r, cp, min_w0_, &pieces);
  cp.set_coefficients(best.theta);
  if (v_model) *v_model = r.model(best.w, best.b, cp, rate_);
  // The joint fixed point is exact where the hysteresis is representable, but with a misfit it is not the
  // least-squares solution the alternation converges to: on Preisach physics it was better on one seed and worse on
  // another (docs/models.md, "Creep on physics no kind was written from"), so the alternation is the default (creep_on_h_fit: joint, prony only).
  if (iters > 0 && joint) {
    best = iterate_joint_on_h(dd, r, cp, best);
  } else if (iters > 0) {
    best = alternate_on_h(dd, r, cp, best, iters);
    if (alt) *alt = Alternation{cp, best, iters, weight};
  }
  return r.model(best.w, best.b, cp, rate_);
}

// Prony creep on H (linear in its gains): iterates the joint solve to its fixed point, from the voltage-input play
// weights; stops once the weights' shape moves by < 0.1 % (their scale does not change the solve).
EvalResult PiCreepFit::iterate_joint_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best) {
  const CreepParams on_v = cp;
  cp.on_hysteresis = true;
  std::vector<double> w = best.w;
  bool moved = false;
  for (int it = 0; it < opt_.joint_iterations; ++it) {
    EvalResult cr = evaluate_joint_on_h(d, r, w, cp, min_w0_);
    report("PI + creep fit");
    double sw = 0, sn = 0, diff = 0, lag_gain = 0;
    for (std::size_t i = 0; i < w.size(); ++i) sw += w[i], sn += cr.w[i];
    if (!(sw > 0 && sn > 0)) break;
    for (std::size_t i = 0; i < w.size(); ++i) diff += std::abs(cr.w[i] / sn - w[i] / sw);
    // With A = Σ w'·F and H_prev = c·A (c = sw/sn once the shapes agree): y = (1 − c·G)·A + c·Σ θ_j·LP_j(A),
    // G = Σθ; so the model's weights are (1 − c·G)·w' and its gains c·θ/(1 − c·G).
    const double c = sw / sn;
    for (double x : cr.theta) lag_gain += x;
    const double direct = 1.0 - c * lag_gain;
    if (!(direct > 0.05)) break;  // creep as large as H itself: not a creep the iteration can represent
    for (double& x : cr.w) x *= direct;
    for (double& x : cr.theta) x *= c / direct;
    cp.set_coefficients(cr.theta);
    w = cr.w;
    best = cr;
    moved = true;
    if (diff < 1e-3) break;
  }
  if (!moved) cp = on_v;  // the voltage-input solution stands
  return best;
}

// Creep on H is bilinear (w and g): alternates the two linear problems, refining the law's nonlinear parameters
// once per round, starting from the voltage-input solution.
EvalResult PiCreepFit::alternate_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters) {
  cp.on_hysteresis = true;
  // Voltage-input gains are in nm/V; as gains on H they are about (nm/V)/(Σw) nm/nm.
  double sum_w = 0;
  for (double x : best.w) sum_w += x;
  std::vector<double> theta = best.theta;
  for (double& t : theta) t /= std::max(1e-12, sum_w);
  cp.set_coefficients(theta);
  return continue_on_h(d, r, cp, best, iters);
}

// `iters` more rounds of the alternation from the play weights best.w and the law cp.
EvalResult PiCreepFit::continue_on_h(const FitData& d, const Basis& r, CreepParams& cp, EvalResult best, int iters) {
  std::vector<double> w = best.w;
  for (int it = 0; it < iters; ++it) {
    const std::vector<double> H = hysteresis_series(d, r, w);
    ModeSearchRows kept;
    search_creep_law(cp, [&](const CreepParams& c) { return evaluate_creep_on_h(d, H, w, c, &kept).sse; }, true);
    EvalResult cr = evaluate_creep_on_h(d, H, w, cp);
    report("PI + creep fit");
    cp.set_coefficients(cr.theta);
    w = cr.w;
    best = evaluate_w_given_creep_on_h(d, r, cp, min_w0_);
    report("PI + creep fit");
    w = best.w;
  }
  return best;
}

// Searches the law's nonlinear parameters (t1, α or the τ_j) for the least SSE of `sse_fn`; refine_only: near the
// current values. Prony and no creep are linear in their weights: nothing to search.
void PiCreepFit::search_creep_law(CreepParams& cp, const SseFn& sse_fn, bool refine_only) {
  const SseFn sse_of = [&](const CreepParams& c) {
    report("PI + creep fit");
    return sse_fn(c);
  };
  // A warm start (the law given as a start, refit_options) searches as the alternation's refinements do: near the
  // given values (a backfitting refit, whose data moved little; the alternation on H that follows refines them
  // again), not over the whole range.
  refine_only = refine_only || opt_.warm_start;
  switch (kind_) {
    case CreepKind::kNone:
    case CreepKind::kProny: break;
    case CreepKind::kLog: search_log_t1(cp, sse_of, refine_only); break;
    case CreepKind::kFractional: search_alpha(cp, sse_of, refine_only); break;
    case CreepKind::kLti: search_lti_taus(cp, sse_of, refine_only); break;
  }
}

void PiCreepFit::search_log_t1(CreepParams& cp, const SseFn& sse_of, bool refine_only) const {
  if (opt_.t1_given && !opt_.warm_start) return;  // fixed
  const double cur = std::log10(cp.t1_s), lo = std::log10(tau_lo_), hi = std::log10(tau_hi_) - 1.0;
  if (!(hi > lo)) return;
  const auto sse_at = [&](double lg) {
    CreepParams c = cp;
    c.t1_s = std::pow(10.0, lg);
    c.decades = log_decades(c.t1_s);
    return sse_of(c);
  };
  cp.t1_s = std::pow(10.0, search_1d(sse_at, refine_only ? std::max(lo, cur - 0.3) : lo,
                                     refine_only ? std::min(hi, cur + 0.3) : hi, refine_only ? 5 : 15, 12));
  cp.decades = log_decades(cp.t1_s);
}

void PiCreepFit::search_alpha(CreepParams& cp, const SseFn& sse_of, bool refine_only) const {
  if (opt_.alpha_given && !opt_.warm_start) return;  // fixed (initial_creep set it)
  const double cur = cp.alpha;
  cp.alpha = search_1d([&](double al) { CreepParams c = cp; c.alpha = al; return sse_of(c); },
                       refine_only ? std::max(0.02, cur - 0.1) : 0.03, refine_only ? std::min(0.98, cur + 0.1) : 0.97,
                       refine_only ? 5 : 19, 12);
}

void PiCreepFit::search_lti_taus(CreepParams& cp, const SseFn& sse_of, bool refine_only) const {
  const double lo = std::log10(tau_lo_), hi = std::log10(tau_hi_);  // the start: initial_creep
  const int rounds = refine_only ? 1 : opt_.search_rounds;
  for (int round = refine_only ? 1 : 0; round < (refine_only ? 2 : rounds) && !opt_.fix_taus; ++round)
    for (std::size_t j = 0; j < cp.taus_s.size(); ++j) {
      auto f = [&](double lg) { CreepParams c = cp; c.taus_s[j] = std::pow(10.0, lg); return sse_of(c); };
      const double cur = std::log10(cp.taus_s[j]);
      // First round scans the whole range; later rounds refine around the current value.
      const double a = round == 0 ? lo : std::max(lo, cur - 0.5), b = round == 0 ? hi : std::min(hi, cur + 0.5);
      cp.taus_s[j] = std::pow(10.0, search_1d(f, a, b, 11, 10));
    }
  std::sort(cp.taus_s.begin(), cp.taus_s.end());
}

// Thresholds: given, or n_play given, or chosen by the validation error of PI + a prony spectrum on the voltage
// (one linear solve per candidate; the choice is not blurred by creep a plain PI cannot follow); for the PI kinds,
// with and without the input map (option input_map: auto). The fewest pieces within 0.2 % of the best.
Basis PiCreepFit::choose_play_count() {
  // The input map's candidates: the PI kinds with a validation part try both (auto); given on or off, that one.
  std::vector<bool> maps{opt_.input_map == "on"};
  if (opt_.input_map == "auto" && !preisach_ && val_) maps = {false, true};
  std::vector<std::vector<double>> counts;
  if (opt_.thresholds_given) counts.push_back(opt_.thresholds_v);
  else if (opt_.n_play_given || !val_) counts.push_back(thresholds_for(ax_.voltage_v, opt_.n_play));
  else
    // The preisach kinds have ~n·K/2 pieces: up to 20 play operators (K ≤ 12: 138 pieces).
    for (int n : {4, 6, 8, 12, 16, 20, 24, 32}) {
      if (static_cast<std::size_t>(n) * 20 > ax_.voltage_v.size() || (preisach_ && n > 20)) break;
      if (!preisach_ && n == 20) continue;
      counts.push_back(thresholds_for(ax_.voltage_v, n));
    }
  if (counts.empty()) counts.push_back(thresholds_for(ax_.voltage_v, 4));
  std::vector<Basis> bases;
  for (const auto& c : counts)
    for (bool map : maps) bases.push_back(basis_n(c, map));
  if (bases.size() == 1) return bases.front();
  CreepParams proxy;
  if (kind_ != CreepKind::kNone) {
    proxy.kind = CreepKind::kProny;
    proxy.tau_min_s = tau_lo_;
    proxy.tau_max_s = tau_hi_;
    proxy.modes_per_decade = 1;
  }
  std::vector<double> score;
  for (const Basis& b : bases) {
    const EvalResult e = evaluate(d_, b, proxy, min_w0_);
    report("PI thresholds");
    CreepParams c = proxy;
    c.set_coefficients(e.theta);
    score.push_back(validation_score(*b.model(e.w, e.b, c, rate_), req_, val_hold_).all);
  }
  // The fewest pieces within 0.2 % of the best (without the map first on a tie).
  const double best = *std::min_element(score.begin(), score.end());
  std::size_t chosen = 0;
  for (std::size_t k = 0; k < bases.size(); ++k)
    if (score[k] <= 1.002 * best &&
        (score[chosen] > 1.002 * best || bases[k].pieces() < bases[chosen].pieces()))
      chosen = k;
  return bases[chosen];
}

// Creep input by validation (auto), else as given; `score` is the chosen model's validation score.
std::unique_ptr<PiCreepModel> PiCreepFit::choose_creep_input(const Basis& r, Score& score) {
  if (opt_.creep_input != "auto") {
    auto m = fit_with(d_, r, opt_.creep_input == "hysteresis", opt_.alternations, nullptr, nullptr, &alt_plain_);
    if (val_) score = validation_score(*m, req_, val_hold_);
    return m;
  }
  std::unique_ptr<PiCreepModel> mv;
  auto mh = fit_with(d_, r, true, opt_.alternations, nullptr, &mv, &alt_plain_);
  std::vector<double> ev, eh;
  const Score sv = validation_score(*mv, req_, val_hold_, &ev), sh = validation_score(*mh, req_, val_hold_, &eh);
  // Creep on V only when validation shows it clearly better: a lead of V within the noise floor can pick it where
  // against the truth H leaves far less at the end of a hold (docs/models.md, "Creep on physics no kind was written
  // from"). Blocks of 5 min; with under 20 min of validation the lower MAE decides (forcing H there costs the short
  // stages of the stage matrix much more than it gains).
  const bool use_h = !validation_prefers(ev, eh, static_cast<std::size_t>(300.0 * rate_));
  score = use_h ? sh : sv;
  return use_h ? std::move(mh) : std::move(mv);
}

// Hold weighting: holds get the weight of the walk samples in total (capped at 10×), kept only when validation
// shows the holds improve and the walk error does not grow by more than 5 %. Returns the factor kept (1: none);
// `weight` holds the per-sample weights it was fitted with.
double PiCreepFit::choose_hold_weight(const Basis& r, const Score& score, const std::vector<char>& train_hold,
                                      std::unique_ptr<PiCreepModel>& m, std::vector<double>& weight) {
  const double n_hold = double(std::count(train_hold.begin(), train_hold.end(), 1));
  const double n_walk = double(train_hold.size()) - n_hold;
  double factor = 1.0;
  if (opt_.hold_weight == "auto") {
    if (val_ && n_hold > 0 && n_walk > 0) factor = std::min(10.0, std::max(1.0, n_walk / n_hold));
  } else if (opt_.hold_weight != "off") {
    factor = opt_.hold_weight_factor;
  }
  if (!(factor > 1.0 && kind_ != CreepKind::kNone && n_hold > 0)) return 1.0;
  weight.resize(train_hold.size());
  for (std::size_t t = 0; t < weight.size(); ++t) weight[t] = train_hold[t] ? factor : 1.0;
  auto mw = fit_with(d_, r, m->creep().on_hysteresis, opt_.alternations, &weight, nullptr, &alt_weighted_);
  bool keep = opt_.hold_weight != "auto";
  if (!keep) {
    const Score sw = validation_score(*mw, req_, val_hold_);
    keep = std::isfinite(sw.hold) && std::isfinite(score.hold) && sw.hold < score.hold && !(sw.walk > 1.05 * score.walk);
  }
  if (!keep) return 1.0;
  m = std::move(mw);
  return factor;
}

// With everything chosen: the final alternations, or (refit_with_validation: true) the final weights from the
// training and validation parts together (one recording in time: slow creep modes get hours more data). The refit
// is off by default: the validation metrics stored with the model and compared by --model auto would then be
// in-sample.
void PiCreepFit::final_fit(const Basis& r, double used_factor, const std::vector<double>& weight,
                           const std::vector<char>& train_hold, std::unique_ptr<PiCreepModel>& m) {
  const bool refit = val_ && opt_.refit_with_validation;
  const bool realternate = opt_.final_alternations != opt_.alternations && m->creep().on_hysteresis &&
                           !(kind_ == CreepKind::kProny && opt_.joint_on_h);
  // The chosen fit's alternation continues (the same result as starting over, without its first rounds again).
  if (realternate && !refit)
    m = fit_with(d_, r, true, opt_.final_alternations, used_factor > 1.0 ? &weight : nullptr, nullptr,
                 used_factor > 1.0 ? &alt_weighted_ : &alt_plain_);
  if (!refit) return;
  std::vector<double> all_v = ax_.voltage_v, all_y = ax_.position_nm, all_w;
  all_v.insert(all_v.end(), val_->voltage_v.begin(), val_->voltage_v.end());
  all_y.insert(all_y.end(), val_->position_nm.begin(), val_->position_nm.end());
  for (std::size_t t = 0; t < all_v.size(); ++t) {
    const bool hold = t < train_hold.size() ? train_hold[t] : val_hold_[t - train_hold.size()];
    all_w.push_back(hold ? used_factor : 1.0);
  }
  FitData all = d_;
  all.v = &all_v, all.y = &all_y;
  m = fit_with(all, r, m->creep().on_hysteresis, opt_.final_alternations, used_factor > 1.0 ? &all_w : nullptr);
}

models::ModelPtr PiCreepFit::run() {
  const Basis r = choose_play_count();
  Score score;
  std::unique_ptr<PiCreepModel> m = choose_creep_input(r, score);
  const std::vector<char> train_hold = fit_hold_rows(*req_.train, req_.axis);
  std::vector<double> weight;
  const double used_factor = choose_hold_weight(r, score, train_hold, m, weight);
  final_fit(r, used_factor, weight, train_hold, m);
  m->meta = make_meta(req_);
  m->meta.validation["fit_hold_weight"] = used_factor;
  m->meta.validation["fit_play_operators"] = static_cast<double>(r.r.size());
  if (preisach_) m->meta.validation["fit_preisach_pieces"] = static_cast<double>(r.pieces());
  else m->meta.validation["fit_input_map_pieces"] = r.input_map ? static_cast<double>(r.knots[0].size() + 1) : 0.0;
  if (kind_ != CreepKind::kNone) m->meta.validation["fit_creep_on_hysteresis"] = m->creep().on_hysteresis ? 1 : 0;
  return m;
}

}  // namespace
}  // namespace pi

// Scale-free by construction: thresholds from the data's own voltage span, normal equations solved on unit
// diagonal, creep time constants only where the data can identify them (≥ 2 samples, ≤ the training duration).
// With a validation part, the number of play operators, the creep input (V or H) and hold weighting are chosen by
// free-run validation error, unless given as options.
// The preisach kinds cut each play output at knots (basis_for); K, the knot intervals over the span, is the number of
// play operators unless given (knots_per_span), so the plane is tiled by an n × n triangle of ramp hysterons.
models::ModelPtr fit_pi_creep(const FitRequest& req, models::CreepKind kind, bool preisach) {
  const std::string map = output_map_option(req.options);
  const FitFn fit = [kind, preisach](const FitRequest& r) -> models::ModelPtr { return pi::PiCreepFit(r, kind, preisach).run(); };
  if (map == "off") return fit(req);
  return fit_with_output_map(req, map == "on", fit);
}

YAML::Node refit_options(const models::Model& previous, const YAML::Node& options, bool same_structure) {
  YAML::Node o = options && options.IsMap() ? YAML::Clone(options) : YAML::Node(YAML::NodeType::Map);
  const models::PiCreepModel* pc = previous.pi_family();
  if (!pc) return o;
  const CreepParams& cp = pc->creep();
  // Same structure: the previous play thresholds, creep input and maps, so that refits compared with each other
  // (a lag profile) differ only by the data, not by a structure chosen again on it.
  if (same_structure) {
    if (!o["thresholds_v"]) o["thresholds_v"] = pc->thresholds_v();
    if (!o["creep_input"] && cp.kind != CreepKind::kNone) o["creep_input"] = cp.on_hysteresis ? "hysteresis" : "voltage";
    if (!o["input_map"] && !pc->preisach()) o["input_map"] = pc->has_input_map() ? "on" : "off";
    if (!o["output_map"]) o["output_map"] = pc->output_map().empty() ? "off" : "on";
  }
  // Otherwise only the law: the play count, creep input and hold weight are chosen again, as the base that absorbed
  // an effect is not the structure to keep (docs/closing-the-loop.md, backfitting).
  if (o["taus_s"] || o["t1_s"] || o["alpha"]) return o;
  switch (cp.kind) {
    case CreepKind::kLti: o["taus_s"] = cp.taus_s; break;
    case CreepKind::kLog: o["t1_s"] = cp.t1_s; break;
    case CreepKind::kFractional: o["alpha"] = cp.alpha; break;
    case CreepKind::kNone:
    case CreepKind::kProny: return o;  // nothing to search
  }
  o["warm_start"] = true;
  return o;
}

}  // namespace piezo::training
