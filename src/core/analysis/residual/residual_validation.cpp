// Validation of effect terms: fit on TRAIN's first part, score on the rest; a family's variant refined there.
#include "piezo_compensation/analysis/residual/residual_validation.h"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "piezo_compensation/analysis/evaluation/evaluation.h"
#include "piezo_compensation/training/fit_common.h"

namespace piezo::analysis::detail {

using models::EffectTerm;

Validator::Validator(const Context& c, std::size_t n_fit, const AcceptanceThresholds& t,
                     std::function<void(const std::string&)> log)
    : c_(c), n_fit_(n_fit), n_(c.x_base.size()), t_(t), log_(std::move(log)), holds_(hold_mask(*c.data)) {
  for (std::size_t i = n_fit_; i < n_; ++i) n_val_hold_ += holds_[i] != 0;
  paired_block_ = std::max<std::size_t>(1, static_cast<std::size_t>(std::lround(t.paired_block_s * c.fs)));
}

Val Validator::validate(std::vector<EffectTerm> terms) const {
  Level off;
  fit_terms(c_, terms, off, 0, n_fit_);
  const std::vector<double> pred = corrected(c_, terms, off);
  Val v;
  double sh = 0;
  const std::size_t mid = n_fit_ + (n_ - n_fit_) / 2;
  for (std::size_t i = n_fit_; i < n_; ++i) {
    const double d = c_.measured[i] - pred[i], e = std::fabs(d);
    v.abs_err.push_back(e);
    v.mae += e;
    v.mse += d * d;
    (i < mid ? v.mae1 : v.mae2) += e;  // the two halves of the validation part, in the same pass
    if (holds_[i]) sh += e;
  }
  if (mid > n_fit_) v.mae1 /= static_cast<double>(mid - n_fit_);
  if (n_ > mid) v.mae2 /= static_cast<double>(n_ - mid);
  v.mae /= static_cast<double>(n_ - n_fit_);
  v.mse /= static_cast<double>(n_ - n_fit_);
  v.hold_mae = n_val_hold_ ? sh / static_cast<double>(n_val_hold_) : 0.0;
  return v;
}

std::vector<double> Validator::block_mae(const std::vector<double>& abs_err) const {
  const std::size_t k = abs_err.size() / paired_block_;
  if (k < 4) return {mean_of(abs_err, 0, abs_err.size())};
  std::vector<double> m(k, 0.0);
  for (std::size_t i = 0; i < k * paired_block_; ++i) m[i / paired_block_] += abs_err[i] / static_cast<double>(paired_block_);
  return m;
}

AcceptanceRound Validator::round(const Val& now) const {
  AcceptanceRound r;
  r.validation_has_holds = n_val_hold_ > 0;
  const double b = std::max(1.0, t_.resolution_block_s * c_.fs);
  r.block_noise_nm = c_.noise_sigma_nm / std::sqrt(b);
  r.systematic_nm = std::sqrt(std::max(0.0, now.mse - c_.noise_sigma_nm * c_.noise_sigma_nm));
  r.noise_sigma_nm = c_.noise_sigma_nm;
  r.block_mae = block_mae(now.abs_err);
  return r;
}

namespace {
Val score_candidate(const Validator& v, const std::vector<EffectTerm>& fixed, const Candidate& cand) {
  std::vector<EffectTerm> trial = fixed;
  for (const auto& t : cand.terms) trial.push_back(t);
  return v.validate(trial);
}
}  // namespace

// The output gain with f linear is the default; another form must be clearly better (paired blocks), a quadratic
// also by AcceptanceThresholds::quadratic_form_margin: a form that wins by a hair on validation can still be far
// off in TEST (docs/validation/residual-loop.md, "Additive and gain effects").
void Validator::choose_gain_form(FamilyScore& s, const std::vector<EffectTerm>& fixed, Val& v) const {
  const Candidate base_cand = s.best;
  for (const char* scales : {models::kSignalPosition, models::kSignalVoltage})
    for (const char* form : {"gain", "gain_quadratic"}) {
      Candidate alt = base_cand;
      EffectTerm& t = alt.terms[0];
      t.scales = scales;
      t.type = form;
      t.reference = std::string(scales) == models::kSignalVoltage ? 0.0 : c_.x_at_zero_v;
      t.center.clear(), t.scale.clear(), t.weight.clear();
      if (t.scales == base_cand.terms[0].scales && t.type == base_cand.terms[0].type) continue;
      const Val va = score_candidate(*this, fixed, alt);
      std::ostringstream os;
      os << "    form " << form << " on the " << scales << ": validation MAE " << va.mae << " nm (linear on the output "
         << v.mae << " nm)";
      if (log_) log_(os.str());
      const double need = std::string(form) == "gain_quadratic" ? 1.0 - t_.quadratic_form_margin : 1.0;
      if (va.mae < need * v.mae && training::validation_prefers(va.abs_err, v.abs_err, paired_block_)) {
        v = va;
        s.best = alt;
        s.best.labels["scales"] = scales;
      }
    }
  s.best.labels["form"] = s.best.terms[0].kind() == models::TermKind::kGain ? "linear" : "quadratic";
}

double Validator::train_ms(const std::vector<EffectTerm>& fixed, const Candidate& cand, std::size_t rows) const {
  std::vector<EffectTerm> trial = fixed;
  for (const auto& t : cand.terms) trial.push_back(t);
  Level lv;
  fit_terms(c_, trial, lv, 0, rows);
  const std::vector<double> r = residual_of(c_, trial, lv);
  double ss = 0.0;
  for (std::size_t i = 0; i < rows; ++i) ss += r[i] * r[i];
  return ss / static_cast<double>(rows);
}

// A delay L and a first-order low-pass τ are told apart only by the shape of the response: over slow signals
// both shift it by about L + τ, so a coarse grid confounds them (a 90-s first-order lag read as 120 s of delay and
// a 35-s low-pass). Keeping the mean delay L + τ, the split between them is chosen on the joint fit's RMS over
// rows [0, rows): L' = k·L for k in {0, ¼, ½, ¾}, τ' = τ + (1 − k)·L, within max_time_constant_s. True when it moved.
bool Validator::split_delay(FamilyScore& s, const std::vector<EffectTerm>& fixed, std::size_t rows, std::size_t q) const {
  const EffectTerm& t0 = s.best.terms[q];
  if (!(t0.lag_s > 0.0) || t0.signal == models::kSignalPosition || t0.kind() == models::TermKind::kSinCos) return false;
  double best_ms = train_ms(fixed, s.best, rows);
  Candidate best = s.best;
  for (double k : {0.0, 0.25, 0.5, 0.75}) {
    Candidate alt = s.best;
    EffectTerm& t = alt.terms[q];
    const double tau = t.time_constant_s + (1.0 - k) * t.lag_s;
    if (max_time_constant_s() > 0.0 && tau > max_time_constant_s()) continue;
    t.lag_s = k * t.lag_s;
    t.time_constant_s = tau;
    t.center.clear(), t.scale.clear(), t.weight.clear();
    const double ms = train_ms(fixed, alt, rows);
    if (ms < best_ms * (1.0 - 1e-4)) best_ms = ms, best = alt;
  }
  if (best.terms[q].lag_s == t0.lag_s) return false;
  if (log_) {
    std::ostringstream os;
    os << "    " << s.family << ": delay " << t0.lag_s << " s + low-pass " << t0.time_constant_s << " s -> "
       << best.terms[q].lag_s << " s + " << best.terms[q].time_constant_s << " s (the same mean delay)";
    log_(os.str());
  }
  s.best = best;
  if (s.best.terms.size() == 1 || q == 0) {
    s.best.parameters["lag_s"] = s.best.terms[q].lag_s;
    s.best.parameters["time_constant_s"] = s.best.terms[q].time_constant_s;
  }
  return true;
}

// The grid's low-pass is a factor ~3 off at worst (a 20-s thermal lag read through 30 s leaves a phase error of
// ~11° on a 200-s cycle, ~10 nm on a 90-nm swing): each term's time constant is refined by a pattern search in
// log τ (factor 2, then √2, … down to 1.1; within a factor `span` of where it starts) on the RMS of the joint fit
// over rows [0, rows), and never past max_time_constant_s (nor below the start for that cap): a longer τ is one the
// validation rows cannot judge. For the decision (score) the rows are the fit part only, from the grid's choice
// within a factor 4, so τ is not chosen on the rows that then judge it; the accepted effect's τ is refined again
// over all of TRAIN (finalise_time_constants: more rows, so τ is not chosen on the noise), from the validated τ
// within a factor √2 only, so the model's τ stays near the one the validation judged (docs/closing-the-loop.md).
bool Validator::refine_time_constants(FamilyScore& s, const std::vector<EffectTerm>& fixed, std::size_t rows,
                                      double span) const {
  bool refined = false;
  for (std::size_t q = 0; q < s.best.terms.size(); ++q) {
    refined = split_delay(s, fixed, rows, q) || refined;
    if (!(s.best.terms[q].time_constant_s > 0.0)) continue;
    const double tau0 = s.best.terms[q].time_constant_s;
    const double tau_max = std::max(tau0, std::min(span * tau0, max_time_constant_s()));
    double best_ms = train_ms(fixed, s.best, rows);
    for (double f = std::min(2.0, span); f > 1.1; f = std::sqrt(f)) {
      for (bool moved = true; moved;) {
        moved = false;
        for (double k : {f, 1.0 / f}) {
          const double tau = s.best.terms[q].time_constant_s * k;
          if (tau > tau_max * (1 + 1e-9) || tau < tau0 / span * (1 - 1e-9)) continue;
          Candidate alt = s.best;
          alt.terms[q].time_constant_s = tau;
          alt.terms[q].center.clear(), alt.terms[q].scale.clear(), alt.terms[q].weight.clear();
          const double ms = train_ms(fixed, alt, rows);
          if (ms < best_ms * (1.0 - 1e-4)) {
            best_ms = ms;
            s.best = alt;
            moved = refined = true;
            break;
          }
        }
      }
    }
    if (s.best.terms.size() == 1 || q == 0) s.best.parameters["time_constant_s"] = s.best.terms[q].time_constant_s;
  }
  return refined;
}

void Validator::fill_sizes(FamilyScore& s, const Val& v, const Val& now) const {
  s.validation_gain = 1.0 - v.mae / now.mae;
  s.hold_validation_gain = n_val_hold_ ? 1.0 - v.hold_mae / now.hold_mae : 0.0;
  s.validation_gain_halves = {1.0 - v.mae1 / now.mae1, 1.0 - v.mae2 / now.mae2};
  // Worse in a half only counts when it is clearly worse there (paired blocks; with under four blocks in the
  // half the lower mean decides, as a plain comparison would).
  const std::size_t nv = std::min(v.abs_err.size(), now.abs_err.size()), h = nv / 2;
  auto part = [](const std::vector<double>& e, std::size_t b, std::size_t en) {
    return std::vector<double>(e.begin() + static_cast<long>(b), e.begin() + static_cast<long>(en));
  };
  s.half_clearly_worse = training::validation_prefers(part(now.abs_err, 0, h), part(v.abs_err, 0, h), paired_block_) ||
                         training::validation_prefers(part(now.abs_err, h, nv), part(v.abs_err, h, nv), paired_block_);
  const double s2 = c_.noise_sigma_nm * c_.noise_sigma_nm;
  const AcceptanceRound r = round(now);
  // The systematic error without it, floored at what a 30-s mean resolves (a base at the noise floor).
  const double sys_now = std::max(now.mse - s2, r.block_noise_nm * r.block_noise_nm);
  const double removed = now.mse - v.mse;
  s.removed_fraction = removed / sys_now;
  s.removed_nm = std::copysign(std::sqrt(std::fabs(removed)), removed);
  s.systematic_nm = std::sqrt(std::max(0.0, v.mse - s2));
  s.clearly_better = training::validation_prefers(v.abs_err, now.abs_err, paired_block_);
  s.block_mae = block_mae(v.abs_err);
  s.parameters = 0;
  for (const auto& t : s.best.terms) s.parameters += t.num_regressors();
}

void Validator::log_score(const FamilyScore& s) const {
  if (!log_) return;
  std::ostringstream os;
  os << "  validation of " << s.family;
  for (const auto& [k, x] : s.best.parameters) os << " " << k << "=" << x;
  for (const auto& [k, x] : s.best.labels) os << " " << k << "=" << x;
  os.precision(3);
  os << ": MAE gain " << 100.0 * s.validation_gain << " %";
  if (n_val_hold_) os << ", in holds " << 100.0 * s.hold_validation_gain << " %";
  os << " (halves " << 100.0 * s.validation_gain_halves.first << " / " << 100.0 * s.validation_gain_halves.second
     << " %); systematic error removed " << 100.0 * s.removed_fraction << " % (" << s.removed_nm << " nm, left "
     << s.systematic_nm << " nm), " << (s.clearly_better ? "clearly better" : "not clearly better") << " (paired blocks)";
  log_(os.str());
}

// Another axis enters through its best-known position (its fused column); its voltage only where it explains clearly
// more on validation than that position with the same lag and low-pass.
void Validator::prefer_fused_position(FamilyScore& s, const std::vector<EffectTerm>& fixed, Val& v) const {
  const auto sig = s.best.labels.find("signal");
  if (sig == s.best.labels.end()) return;
  const std::string volt = sig->second, other = io::voltage_column_axis(volt);
  if (other.empty()) return;
  const std::string fused = io::fused_position_column(other);
  if (std::find(c_.other_axes.begin(), c_.other_axes.end(), fused) == c_.other_axes.end()) return;
  // Only the terms on that voltage change; a gain on the fused position standardises it by TRAIN's mean and SD.
  const auto [mu, sd] = signal_stats(c_, fused);
  if (!(sd > 0)) return;
  Candidate alt = s.best;
  alt.terms.clear();
  for (EffectTerm t : s.best.terms) {
    if (t.signal == volt && t.kind() == models::TermKind::kPlay) continue;  // a play's threshold is in volts
    if (t.signal == volt) {
      t.signal = fused;
      if (t.is_gain()) t.pre_center = mu, t.pre_scale = sd;
      t.center.clear(), t.scale.clear(), t.weight.clear();
    }
    alt.terms.push_back(t);
  }
  alt.labels["signal"] = fused;
  alt.parameters.erase("play_threshold_v");
  const Val va = score_candidate(*this, fixed, alt);
  if (log_) {
    std::ostringstream os;
    os << "    " << s.family << " on " << fused << ": validation MSE " << va.mse << " nm² (" << volt << ": " << v.mse
       << " nm²)";
    log_(os.str());
  }
  // The fused position is the coupling's physical form; the voltage (with a play for the other axis' hysteresis,
  // one regressor more) stays only where its validation errors are clearly lower (paired blocks).
  if (!training::validation_prefers(v.abs_err, va.abs_err, paired_block_)) {
    s.best = alt;
    v = va;
  }
}

void Validator::score(FamilyScore& s, const std::vector<EffectTerm>& fixed, const Val& now, bool choose_form) const {
  Val v = score_candidate(*this, fixed, s.best);
  if (traits_of(s.family).id == Family::kCrossAxis || traits_of(s.family).id == Family::kCrossAxisGain)
    prefer_fused_position(s, fixed, v);
  if (is_gain_family(s.family) && choose_form) choose_gain_form(s, fixed, v);
  if (refine_time_constants(s, fixed, n_fit_, 4.0)) v = score_candidate(*this, fixed, s.best);
  fill_sizes(s, v, now);
  log_score(s);
}

void Validator::finalise_time_constants(FamilyScore& s, const std::vector<EffectTerm>& fixed) const {
  const Candidate validated = s.best;
  if (!refine_time_constants(s, fixed, n_, std::sqrt(2.0)) || !log_) return;
  std::ostringstream os;
  os << "  " << s.family << ": time constant refined over all of TRAIN:";
  for (std::size_t q = 0; q < s.best.terms.size(); ++q)
    if (s.best.terms[q].time_constant_s != validated.terms[q].time_constant_s)
      os << " " << validated.terms[q].time_constant_s << " -> " << s.best.terms[q].time_constant_s << " s";
  log_(os.str());
}

}  // namespace piezo::analysis::detail
