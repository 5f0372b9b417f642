// The residual loop: score every effect family on the current residual, let the acceptance policy pick at most
// one, add it and backfit, repeat; then assess what is left on TEST. The parts: the family table and candidate
// generators (residual_families.cpp), scoring (residual_scoring.cpp), validation (residual_validation.cpp), the
// acceptance policy (residual_acceptance.cpp), the Backfitter (residual_backfit.cpp), the remainder assessment
// (residual_remainder.cpp).
#include "piezo_compensation/analysis/residual/residual.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <numeric>
#include <sstream>
#include <stdexcept>

#include "piezo_compensation/analysis/residual/estimator_fit.h"
#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/analysis/evaluation/noise_floor.h"
#include "piezo_compensation/analysis/residual/residual_backfit.h"
#include "piezo_compensation/analysis/residual/residual_context.h"
#include "piezo_compensation/models/model_stream.h"
#include "piezo_compensation/analysis/residual/residual_validation.h"
#include "piezo_compensation/models/augmented_model.h"
#include "piezo_compensation/models/pi_model.h"
#include "piezo_compensation/util/flush_subnormals.h"

namespace piezo::analysis {

using models::EffectTerm;
using namespace detail;

bool continues_in_time(const io::Dataset& prev, const io::Dataset& next) {
  if (prev.size() < 2 || next.empty()) return false;
  const double dt = prev.time_s[1] - prev.time_s[0];
  return std::fabs(next.time_s.front() - (prev.time_s.back() + dt)) < 0.5 * dt;
}

namespace {

std::vector<double> run_model(models::Model& m, const io::Dataset& d, const std::string& axis, PredictionMode mode) {
  models::StreamOptions so;
  so.mode = mode;
  return models::stream_model(m, d, axis, so).prediction;
}

// Time constants of the start-state transients: the base's own creep modes that TRAIN can see decay (τ from 5 s
// to twice its duration; longer ones are an offset over TRAIN), or, for a base without modes, a decade grid in
// the same range.
std::vector<double> start_transient_taus(const models::Model& base, const io::Dataset& train) {
  const double duration = train.time_s.back() - train.time_s.front();
  std::vector<double> taus = base.creep_mode_taus_s();
  if (taus.empty()) taus = {10.0, 100.0, 1000.0};
  std::vector<double> out;
  for (double t : taus)
    if (t >= 5.0 && t <= 2.0 * duration) out.push_back(t);
  std::sort(out.begin(), out.end());
  return out;
}

// Where a stroke gain acts about: the stage's position at 0 V. The base at rest at 0 V after a reset is a virgin
// state the stage need not be in (hysteresis leaves it anywhere within the loop at 0 V); the mean of what the stage
// did at 0 V is read from the data: a straight line through the measured positions of the rows within ±2.5 % of
// the voltage span of 0 V, taken at 0 V (the line removes the slope across the band, so the band's width matters
// little). Where the data come near 0 V in fewer than max(200, 0.5 % of the rows) rows, `fallback`.
double position_at_zero_volts(const std::vector<double>& v, const std::vector<double>& y, double fallback) {
  const double band = 0.025 * span_of(v);
  double n = 0, sv = 0, sy = 0, svv = 0, svy = 0;
  for (std::size_t i = 0; i < v.size(); ++i)
    if (std::fabs(v[i]) <= band) n += 1, sv += v[i], sy += y[i], svv += v[i] * v[i], svy += v[i] * y[i];
  if (n < std::max(200.0, 0.005 * static_cast<double>(v.size()))) return fallback;
  const double mv = sv / n, my = sy / n, var = svv / n - mv * mv;
  if (!(var > 1e-12 * band * band)) return my;
  return my - (svy / n - mv * my) / var * mv;
}

void check_inputs(const io::Dataset& train, const io::Dataset& test, const ResidualOptions& o) {
  train.validate();
  test.validate();
  if (train.size() < 200)
    throw io::DataError((train.source.empty() ? "TRAIN" : train.source) + ": too few rows for the residual tool (need ≥ 200)");
  if (test.empty()) throw io::DataError((test.source.empty() ? "TEST" : test.source) + ": no rows");
  const double fs = train.sample_rate_hz();
  if (std::fabs(test.sample_rate_hz() / fs - 1.0) > 0.02)
    throw io::DataError("TRAIN and TEST have different sample rates (" + std::to_string(fs) + " vs " +
                        std::to_string(test.sample_rate_hz()) + " Hz)");
  if (!(o.validation_fraction > 0.05 && o.validation_fraction < 0.8))
    throw std::invalid_argument("validation fraction must be in (0.05, 0.8)");
  for (const auto& f : o.families) traits_of(f);
}

// Inputs held at their first values: only the rest position at 0 V matters here.
double stroke_pivot(const models::Model& base, const io::Dataset& train, Context& c, const ResidualOptions& o) {
  models::ModelPtr b = base.clone();
  b->reset(0.0, c.measured[0]);
  models::InputResolver in(train, b->aux_inputs(), o.axis);
  double at_rest = b->predict(models::ModelInput{0.0, in.at(0)});
  if (!std::isfinite(at_rest)) at_rest = mean_of(c.x_base, 0, c.x_base.size());
  const double pivot = position_at_zero_volts(c.voltage, c.measured, at_rest);
  if (o.log) {
    std::ostringstream os;
    os << "stroke-gain pivot: measured position at 0 V " << pivot << " nm (the base at rest at 0 V: " << at_rest << " nm)";
    o.log(os.str());
  }
  return pivot;
}

// Several TRAIN recordings: each one's zero is not an effect. Its mean residual, less the mean over the
// recordings, is taken out of its measured positions before any family is searched (as the fit profiles it out).
void remove_recording_zeros(const io::Dataset& train, Context& c, const ResidualOptions& o) {
  const std::size_t R = train.recording_count();
  if (R < 2) return;
  std::vector<double> d = models::recording_offsets(train, o.axis, c.x_base);
  const double mean = std::accumulate(d.begin(), d.end(), 0.0) / static_cast<double>(R);
  double ss = 0;
  for (std::size_t k = 0; k < R; ++k) {
    const auto [b, e] = train.recording_rows(k);
    for (std::size_t i = b; i < e; ++i) c.measured[i] -= d[k] - mean;
    ss += (d[k] - mean) * (d[k] - mean);
  }
  if (o.log) {
    std::ostringstream os;
    os << "TRAIN has " << R << " recordings: each one's zero taken out of its residual (RMS " << std::sqrt(ss / R) << " nm)";
    o.log(os.str());
  }
}

Context make_context(const models::Model& base, const io::Dataset& train, const io::Dataset& test, const ResidualOptions& o) {
  Context c;
  c.data = &train;
  c.axis = o.axis;
  c.fs = train.sample_rate_hz();
  const auto& ax = train.axis(o.axis);
  c.voltage = ax.voltage_v;
  c.measured = ax.position_nm;
  models::ModelPtr b = base.clone();
  c.x_base = run_model(*b, train, o.axis, o.mode);
  remove_recording_zeros(train, c, o);
  // Another axis enters through its best-known position: its fused column where the caller gave its model
  // (add_fused_positions), else its readings.
  for (const auto& other : train.axes)
    if (other.name != o.axis && test.has_axis(other.name)) {
      c.other_axes.push_back(io::voltage_column(other.name));
      const std::string fused = io::fused_position_column(other.name);
      c.other_axes.push_back(train.find_aux(fused) && test.find_aux(fused) ? fused : io::position_column(other.name));
    }
  c.x_at_zero_v = stroke_pivot(base, train, c, o);
  for (const auto& a : train.aux)
    if (test.find_aux(a.name) && std::find(c.other_axes.begin(), c.other_axes.end(), a.name) == c.other_axes.end())
      c.aux_names.push_back(a.name);
  if (o.start_transients) {
    c.transient_taus_s = start_transient_taus(base, train);
    for (double tau : c.transient_taus_s) {
      std::vector<double> col(train.size());
      for (std::size_t i = 0; i < col.size(); ++i) col[i] = std::exp(-(train.time_s[i] - train.time_s[0]) / tau);
      c.transient.push_back(std::move(col));
    }
  }
  // The reading noise from the data (second differences in holds, else of the base's residual): what the
  // acceptance policy sets every effect's size against.
  c.noise_sigma_nm = estimate_noise_floor(train, o.axis, &c.x_base).sigma_nm;
  return c;
}

std::vector<double> truth_or_empty(const io::Dataset& d, const std::string& axis) {
  const auto& ax = d.axis(axis);
  return ax.has_truth() ? ax.true_position_nm : std::vector<double>{};
}

// The loop's state over one trace_residual call.
class Loop {
 public:
  Loop(const models::Model& base, const io::Dataset& train, const io::Dataset& test, const ResidualOptions& o)
      : o_(o), train_(train), test_(test), c_(make_context(base, train, test, o)),
        n_(train.size()),
        n_fit_(static_cast<std::size_t>(std::lround(static_cast<double>(n_) * (1.0 - o.validation_fraction)))),
        validator_(c_, n_fit_, o.acceptance, o.log), rng_(o.seed), backfitter_(c_, validator_, o, train, rng_),
        base_(base.clone()), truth_test_(truth_or_empty(test, o.axis)), meas_test_(test.axis(o.axis).position_nm) {
    c_.max_time_constant_s = validator_.max_time_constant_s();
  }

  ResidualResult run();

 private:
  void log(const std::string& s) const {
    if (o_.log) o_.log(s);
  }
  std::vector<double> run_test(models::Model& m, const Level& lv);
  // The stage position over TEST: the augmented model without its sensor effects (is_reading_family), which
  // are in the readings only.
  std::vector<double> run_test_position(const std::vector<double>& readings);
  void score_before();
  std::vector<FamilyScore> rank(int step);
  bool step(int step);
  int joint_pair(std::vector<FamilyScore>& ranking, const Val& now);
  int after_one_refit(std::vector<FamilyScore>& ranking, const Val& now);
  // `winner` is an element of `ranking`: the report's ranking shows its variant after the backfits.
  void add_effect(FamilyScore& winner, const std::vector<FamilyScore>& ranking, std::vector<FamilyScore> competitors);
  void finish();
  void rechoose_jointly();
  // Effect q's terms on an auxiliary signal: their lag profiled (Backfitter::profile_lag), the effect's parameters
  // and labels updated; the first such term's profile (empty for other families).
  LagProfile profile_lags(std::size_t q, const std::string& family, std::map<std::string, double>& parameters,
                          std::map<std::string, std::string>& labels);
  // One past effect q's last term.
  std::size_t effect_end(std::size_t q) const { return q + 1 < effect_first_.size() ? effect_first_[q + 1] : terms_.size(); }

  const ResidualOptions& o_;
  const io::Dataset& train_;
  const io::Dataset& test_;
  Context c_;
  std::size_t n_, n_fit_;
  Validator validator_;
  std::mt19937_64 rng_;
  Backfitter backfitter_;
  models::ModelPtr base_;                 // refitted by backfitting when options.refit_base is set
  std::vector<EffectTerm> terms_;         // accepted, fitted on all of TRAIN
  std::vector<std::size_t> effect_first_; // first term index of each effect
  Level level_;
  std::vector<double> truth_test_;
  const std::vector<double>& meas_test_;
  models::StreamOptions test_run_;
  ResidualResult res_;
};

// With start transients and TEST continuing TRAIN, the transients fitted on TRAIN run on into TEST: the base's
// cold-start error is not the model's (a live model has the true history), so it is not scored against it.
std::vector<double> Loop::run_test(models::Model& m, const Level& lv) {
  const models::StreamResult r = models::stream_model(m, test_, o_.axis, test_run_);
  res_.test_first_scored = r.first_scored;
  std::vector<double> p = r.prediction;
  if (res_.warm_started)
    for (std::size_t j = 0; j < lv.transient_nm.size(); ++j)
      for (std::size_t i = 0; i < p.size(); ++i)
        p[i] += lv.transient_nm[j] * std::exp(-(test_.time_s[i] - train_.time_s[0]) / c_.transient_taus_s[j]);
  return p;
}

std::vector<double> Loop::run_test_position(const std::vector<double>& readings) {
  std::vector<EffectTerm> stage;
  for (const auto& t : terms_)
    if (!is_reading_family(t.family)) stage.push_back(t);
  if (stage.size() == terms_.size()) return readings;
  models::AugmentedModel m(base_->clone(), stage, level_.offset_nm, c_.fs);
  return run_test(m, level_);
}

void Loop::score_before() {
  res_.warm_started = o_.warm_start && continues_in_time(train_, test_);
  res_.anchor_s = o_.anchor_s;
  test_run_.mode = o_.mode;
  test_run_.warmup = res_.warm_started ? &train_ : nullptr;
  test_run_.anchor_s = o_.anchor_s;
  Level lv0;  // the transients alone (no effect terms): the base's TEST error without its cold start
  if (!c_.transient.empty()) {
    std::vector<EffectTerm> none;
    fit_terms(c_, none, lv0, 0, n_);
    lv0.offset_nm = 0.0;  // an offset is not the base's: only the decays are carried
    std::ostringstream os;
    os << "start transients (mid-history): τ";
    for (std::size_t j = 0; j < lv0.transient_nm.size(); ++j)
      os << (j ? ", " : " ") << c_.transient_taus_s[j] << " s: " << lv0.transient_nm[j] << " nm";
    log(os.str());
  }
  models::ModelPtr b = base_->clone();
  res_.test_pred_before = run_test(*b, lv0);
  res_.test_mask.assign(test_.size(), 1);
  for (std::size_t i = 0; i < res_.test_first_scored && i < test_.size(); ++i) res_.test_mask[i] = 0;
  res_.before_test = error_stats(res_.test_pred_before, meas_test_, res_.test_mask);
  if (!truth_test_.empty()) res_.before_test_truth = error_stats(res_.test_pred_before, truth_test_, res_.test_mask);
  std::vector<double> r(n_);
  for (std::size_t i = 0; i < n_; ++i) r[i] = c_.measured[i] - c_.x_base[i];
  res_.before_validation.mae_nm = mae_of(r, n_fit_, n_);
}

// Every family scored on the current residual, best explained variance first.
std::vector<FamilyScore> Loop::rank(int step) {
  const std::vector<double> pred = corrected(c_, terms_, level_);
  std::vector<double> r(n_);
  for (std::size_t i = 0; i < n_; ++i) r[i] = c_.measured[i] - pred[i];
  std::vector<FamilyScore> ranking;
  const std::vector<std::string>& fams = o_.families.empty() ? residual_family_names() : o_.families;
  for (const auto& f : fams) {
    ranking.push_back(score_family(traits_of(f).id, c_, terms_, level_, r, pred, o_, rng_));
    const auto& s = ranking.back();
    std::ostringstream os;
    os << "step " << step + 1 << ": " << f;
    if (!s.available) os << " (" << s.note << ")";
    else os << ": explained variance " << s.explained_variance << ", p " << s.p_value << (s.significant ? " *" : "");
    log(os.str());
  }
  std::stable_sort(ranking.begin(), ranking.end(), [](const FamilyScore& a, const FamilyScore& b) {
    if (a.available != b.available) return a.available;
    return a.explained_variance > b.explained_variance;
  });
  return ranking;
}

// The significant families that name a physical signal (not an operating point, not a line in time), in ranking
// order (best explained variance first), at most `limit`: the candidates of joint_pair and after_one_refit.
std::vector<std::size_t> significant_physical(const std::vector<FamilyScore>& ranking, std::size_t limit) {
  std::vector<std::size_t> sig;
  for (std::size_t i = 0; i < ranking.size() && sig.size() < limit; ++i)
    if (ranking[i].available && ranking[i].significant && !is_operating_point_family(ranking[i].family) &&
        !extrapolates_in_time(ranking[i].family))
      sig.push_back(i);
  return sig;
}

// A gain family and the additive family on the same signal are one effect's two forms, never a pair.
bool same_signal_forms(const std::string& a, const std::string& b) {
  return additive_counterpart(a) == b || additive_counterpart(b) == a;
}

// Two effects at once each leave the other's residual, and the base's distortion by both, in the validation of
// the other: each alone may then fail its rules though the two together pass them. When no family passes alone,
// the significant physical families are validated in pairs (the two strongest by explained variance first, not a
// gain with its own additive family); the stronger of the first pair that passes every rule of a single family is
// added, and the next round judges the other on the backfitted base. -1 when no pair passes.
int Loop::joint_pair(std::vector<FamilyScore>& ranking, const Val& now) {
  const std::vector<std::size_t> sig = significant_physical(ranking, 3);
  if (sig.size() < 2) return -1;
  const AcceptanceRound round = validator_.round(now);
  for (std::size_t a = 0; a < sig.size(); ++a)
    for (std::size_t b = a + 1; b < sig.size(); ++b) {
      const FamilyScore &x = ranking[sig[a]], &y = ranking[sig[b]];
      if (same_signal_forms(x.family, y.family)) continue;
      FamilyScore pair = x;
      for (const auto& t : y.best.terms) pair.best.terms.push_back(t);
      validator_.score(pair, terms_, now, false);
      const Verdict v = judge_alone(pair, o_.acceptance, round);
      log("  " + x.family + " with " + y.family + " validated jointly: " +
          (v.pass ? "passes" : std::string(rule_name(v.rule)) + ": " + v.reason));
      if (!v.pass) continue;
      ranking[sig[a]].verdict = "kept: validated jointly with " + y.family + " (added in the next round if it then passes alone)";
      return static_cast<int>(sig[a]);
    }
  return -1;
}

// A base fitted on data that carry an effect absorbs what its own regressors can express of it (a slow wander of
// another axis projects onto its long creep modes by chance), and the effect's terms fitted on the residual of that
// base then validate poorly. When nothing passes alone or in a pair, the two strongest significant physical
// families, and then the two together, are validated once more with the base refitted on TRAIN without their part
// (as backfitting will do when one is added), against the model as it is; the first that then passes every rule
// is added (of a pair, the stronger; the next round judges the other). -1 when none.
int Loop::after_one_refit(std::vector<FamilyScore>& ranking, const Val& now) {
  if (!o_.refit_base) return -1;
  const std::vector<std::size_t> sig = significant_physical(ranking, 2);
  std::vector<std::vector<std::size_t>> trials;
  for (std::size_t i : sig) trials.push_back({i});
  if (sig.size() == 2 && !same_signal_forms(ranking[sig[0]].family, ranking[sig[1]].family)) trials.push_back(sig);
  const AcceptanceRound round = validator_.round(now);
  for (const auto& trial_set : trials) {
    FamilyScore again = ranking[trial_set[0]];
    std::string names = again.family;
    for (std::size_t k = 1; k < trial_set.size(); ++k) {
      const auto& other = ranking[trial_set[k]];
      again.best.terms.insert(again.best.terms.end(), other.best.terms.begin(), other.best.terms.end());
      names += " with " + other.family;
    }
    const std::vector<double> x_base = c_.x_base;
    models::ModelPtr base = base_->clone();
    std::vector<EffectTerm> trial = terms_;
    trial.insert(trial.end(), again.best.terms.begin(), again.best.terms.end());
    Level lv;
    fit_terms(c_, trial, lv, 0, n_);
    backfitter_.refit_without(trial, lv, base);
    validator_.score(again, terms_, now, false);
    c_.x_base = x_base;  // the refit was a trial: add_effect backfits for real
    const Verdict v = judge_alone(again, o_.acceptance, round);
    log("  " + names + " validated with the base refitted without it: " +
        (v.pass ? "passes" : std::string(rule_name(v.rule)) + ": " + v.reason));
    if (!v.pass) continue;
    ranking[trial_set[0]].verdict = "kept: validated with the base refitted without " + names;
    return static_cast<int>(trial_set[0]);
  }
  return -1;
}

// One round: every significant family is validated (competing explanations are compared on data they were not
// fitted on), the policy picks at most one. False when none is added.
bool Loop::step(int step) {
  std::vector<FamilyScore> ranking = rank(step);
  const Val now = validator_.validate(terms_);
  // A gain's form is chosen after the base has been refitted without it (Backfitter) where the base is refitted:
  // the first base absorbed part of the effect, and what it left looks curved.
  const bool form_now = !(o_.refit_base && std::max(o_.backfit_iterations, o_.gain_backfit_iterations) > 0);
  for (auto& s : ranking)
    if (s.available && s.significant) validator_.score(s, terms_, now, form_now);
  std::vector<FamilyScore> competitors;
  int w = choose_effect(ranking, o_.acceptance, validator_.round(now), &competitors);
  if (w < 0) w = joint_pair(ranking, now);
  if (w < 0) w = after_one_refit(ranking, now);
  if (w < 0) {
    res_.final_ranking = ranking;
    return false;
  }
  add_effect(ranking[static_cast<std::size_t>(w)], ranking, std::move(competitors));
  if (step + 1 == o_.max_effects) res_.final_ranking = ranking;
  return true;
}

void Loop::add_effect(FamilyScore& winner, const std::vector<FamilyScore>& ranking, std::vector<FamilyScore> competitors) {
  validator_.finalise_time_constants(winner, terms_);
  effect_first_.push_back(terms_.size());
  for (const auto& t : winner.best.terms) terms_.push_back(t);
  fit_terms(c_, terms_, level_, 0, n_);
  backfitter_.run(winner, terms_, effect_first_.back(), level_, base_);
  const LagProfile lag_profile =
      profile_lags(effect_first_.size() - 1, winner.family, winner.best.parameters, winner.best.labels);
  FoundEffect e;
  e.family = winner.family;
  e.parameters = winner.best.parameters;
  e.labels = winner.best.labels;
  e.explained_variance = winner.explained_variance;
  e.p_value = winner.p_value;
  e.validation_gain = winner.validation_gain;
  e.hold_validation_gain = winner.hold_validation_gain;
  e.ranking = ranking;
  e.competitors = std::move(competitors);
  models::AugmentedModel m(base_->clone(), terms_, level_.offset_nm, c_.fs);
  e.test_prediction = run_test(m, level_);
  e.lag_profile = lag_profile;
  e.test_after = error_stats(e.test_prediction, meas_test_, res_.test_mask);
  e.in_readings = is_reading_family(e.family);
  if (!truth_test_.empty())
    e.test_after_truth = error_stats(run_test_position(e.test_prediction), truth_test_, res_.test_mask);
  log("added " + e.family + (e.in_readings ? " (a sensor effect: in the readings)" : "") + ": TEST MAE " + std::to_string(e.test_after.mae_nm) + " nm" +
      (truth_test_.empty() ? "" : " (against the truth " + std::to_string(e.test_after_truth.mae_nm) + " nm)"));
  res_.effects.push_back(std::move(e));
}

// The last step: each added effect's variant (signal, lag, low-pass, a gain's form) chosen again given all the others
// (each was chosen while the later ones were still in its residual), kept where it validates better; then all terms
// refitted together.
void Loop::rechoose_jointly() {
  if (effect_first_.size() < 2) return;
  ResidualOptions no_null = o_;
  no_null.permutations = 0;  // accepted effects: only their variants are chosen again
  for (std::size_t q = 0; q < effect_first_.size(); ++q) {
    const std::size_t first = effect_first_[q];
    const std::size_t last = effect_end(q);
    std::vector<EffectTerm> others(terms_.begin(), terms_.begin() + static_cast<long>(first));
    others.insert(others.end(), terms_.begin() + static_cast<long>(last), terms_.end());
    Level lv;
    fit_terms(c_, others, lv, 0, n_);
    const std::vector<double> p_o = corrected(c_, others, lv), r_o = residual_of(c_, others, lv);
    const FoundEffect& e = res_.effects[q];
    FamilyScore again = score_family(traits_of(e.family).id, c_, others, lv, r_o, p_o, no_null, rng_);
    if (!again.available) continue;
    const Val base_val = validator_.validate(others);
    validator_.score(again, others, base_val, is_gain_family(e.family));
    validator_.finalise_time_constants(again, others);
    std::vector<EffectTerm> now_terms = others, new_terms = others;
    now_terms.insert(now_terms.end(), terms_.begin() + static_cast<long>(first), terms_.begin() + static_cast<long>(last));
    new_terms.insert(new_terms.end(), again.best.terms.begin(), again.best.terms.end());
    const double mse_now = validator_.validate(now_terms).mse, mse_new = validator_.validate(new_terms).mse;
    std::ostringstream os;
    os << "  " << e.family << " chosen again given the other effects: validation MSE " << mse_new << " nm² (was "
       << mse_now << " nm²)";
    if (!(mse_new < mse_now)) {
      log(os.str() + ", kept as it was");
      continue;
    }
    log(os.str() + ", changed");
    std::vector<EffectTerm> rebuilt(terms_.begin(), terms_.begin() + static_cast<long>(first));
    rebuilt.insert(rebuilt.end(), again.best.terms.begin(), again.best.terms.end());
    rebuilt.insert(rebuilt.end(), terms_.begin() + static_cast<long>(last), terms_.end());
    const long shift = static_cast<long>(again.best.terms.size()) - static_cast<long>(last - first);
    for (std::size_t k = q + 1; k < effect_first_.size(); ++k)
      effect_first_[k] = static_cast<std::size_t>(static_cast<long>(effect_first_[k]) + shift);
    terms_ = std::move(rebuilt);
    res_.effects[q].parameters = again.best.parameters;
    res_.effects[q].labels = again.best.labels;
    fit_terms(c_, terms_, level_, 0, n_);
  }
  fit_terms(c_, terms_, level_, 0, n_);
}

// The lag of a term on an auxiliary signal (a temperature felt through the mount) as a first-order low-pass, its
// τ profiled at the end with the base refitted for each τ (Backfitter::profile_lag): chosen on the residual of a
// base refitted at another lag, a lag confirms itself (docs/validation/residual-loop.md, "The lag of a slow signal").
LagProfile Loop::profile_lags(std::size_t q, const std::string& family, std::map<std::string, double>& parameters,
                              std::map<std::string, std::string>& labels) {
  LagProfile first_profile;
  const Family f = traits_of(family).id;
  if (f != Family::kAuxSignal && f != Family::kAuxGain) return first_profile;
  const std::size_t first = effect_first_[q], last = effect_end(q);
  for (std::size_t k = first; k < last; ++k) {
    const double was_lag = terms_[k].lag_s, was_tau = terms_[k].time_constant_s;
    const LagProfile profile = backfitter_.profile_lag(terms_, k, level_, base_, validator_.max_time_constant_s());
    std::ostringstream os;
    os << "  " << family << " on " << terms_[k].signal
       << ": first-order lag profiled with the base refitted at each τ (TRAIN RMS):";
    for (const auto& [tau, rms] : profile.points) os << " " << tau << " s " << rms << " nm,";
    os << " was delay " << was_lag << " s + low-pass " << was_tau << " s, now " << profile.chosen_s
       << " s (not clearly worse: " << profile.lo_s << " … " << profile.hi_s << " s)";
    log(os.str());
    if (k != first) continue;
    parameters["lag_s"] = terms_[k].lag_s;
    parameters["time_constant_s"] = terms_[k].time_constant_s;
    parameters["time_constant_lo_s"] = profile.lo_s;
    parameters["time_constant_hi_s"] = profile.hi_s;
    labels["lag_form"] = "first-order, profiled";
    first_profile = profile;
  }
  return first_profile;
}

void Loop::finish() {
  if (effect_first_.size() >= 2) {
    rechoose_jointly();
    backfitter_.refit_all(terms_, level_, base_);
    rechoose_jointly();
    for (std::size_t q = 0; q < effect_first_.size(); ++q) {
      FoundEffect& e = res_.effects[q];
      LagProfile p = profile_lags(q, e.family, e.parameters, e.labels);
      if (!p.empty()) e.lag_profile = std::move(p);
    }
  }
  // Parameters from the final joint fit.
  for (std::size_t q = 0; q < res_.effects.size(); ++q) {
    const std::size_t first = effect_first_[q];
    const std::size_t last = effect_end(q);
    describe(terms_, first, last - first, res_.effects[q]);
  }
  auto model = std::make_unique<models::AugmentedModel>(base_->clone(), terms_, level_.offset_nm, c_.fs);
  res_.test_pred_after = run_test(*model, level_);
  res_.after_test = error_stats(res_.test_pred_after, meas_test_, res_.test_mask);
  res_.test_position_after = run_test_position(res_.test_pred_after);
  if (!truth_test_.empty()) res_.after_test_truth = error_stats(res_.test_position_after, truth_test_, res_.test_mask);
  res_.after_validation.mae_nm = mae_of(residual_of(c_, terms_, level_), n_fit_, n_);
  std::vector<double> r(test_.size());
  for (std::size_t i = 0; i < r.size(); ++i) r[i] = meas_test_[i] - res_.test_pred_after[i];
  res_.remainder = assess_remainder(r, res_.test_pred_after, test_, o_.axis, res_.test_mask, o_.acceptance.alpha);
  log(describe_remainder(res_.remainder));
  res_.model = std::move(model);
}

ResidualResult Loop::run() {
  score_before();
  for (int s = 0; s < o_.max_effects; ++s)
    if (!step(s)) break;
  finish();
  return std::move(res_);
}

}  // namespace

void add_fused_positions(io::Dataset& train, io::Dataset& test,
                         const std::map<std::string, std::shared_ptr<const models::Model>>& models,
                         const std::string& own_axis, bool warm_start, const std::function<void(const std::string&)>& log) {
  const bool continues = warm_start && continues_in_time(train, test);
  for (const auto& [axis, model] : models) {
    if (!model) throw std::invalid_argument("the other-axis model for axis " + axis + " is empty");
    if (axis == own_axis) throw std::invalid_argument("an other-axis model was given for the modelled axis " + axis);
    if (!train.has_axis(axis) || !test.has_axis(axis))
      throw io::DataError("an other-axis model was given for axis " + axis + ", which TRAIN or TEST does not have");
    std::vector<double> ft = fused_position(*model, train, axis);
    std::vector<double> fs = fused_position(*model, test, axis, continues ? &train : nullptr);
    const bool fuses = model->meta.estimator && !model->meta.estimator.IsNull();
    if (log) log("axis " + axis + " enters through its fused position (" + (fuses ? "its model with its encoder" : "its model alone") + ")");
    const std::string col = io::fused_position_column(axis);
    for (io::Dataset* d : {&train, &test})
      if (d->find_aux(col)) throw io::DataError(d->source_or_data() + " already has a column " + col);
    train.aux.push_back({col, std::move(ft)});
    test.aux.push_back({col, std::move(fs)});
  }
}

ResidualResult trace_residual(const models::Model& base, const io::Dataset& train, const io::Dataset& test,
                              const ResidualOptions& o) {
  check_inputs(train, test, o);
  const util::FlushSubnormals flush;  // decaying creep-filter states: see util/flush_subnormals.h
  Loop loop(base, train, test, o);
  return loop.run();
}

}  // namespace piezo::analysis
