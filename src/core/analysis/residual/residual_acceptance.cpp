// The acceptance policy of the residual loop: named rules in order, each a verdict with its reason.
#include "piezo_compensation/analysis/residual/residual_acceptance.h"

#include <cmath>
#include <sstream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "piezo_compensation/analysis/residual/residual_families.h"

namespace piezo::analysis {

namespace {

Verdict pass(AcceptanceRule rule) { return Verdict{true, rule, ""}; }

Verdict refuse(AcceptanceRule rule, const std::string& why) { return Verdict{false, rule, why}; }

std::string pct(double x) {
  std::ostringstream os;
  os.precision(3);
  os << 100.0 * x << " %";
  return os.str();
}

std::string nm(double x) {
  std::ostringstream os;
  os.precision(3);
  os << x << " nm";
  return os.str();
}

bool line_in_time(const FamilyScore& s) { return extrapolates_in_time(s.family); }

// The systematic error a candidate removes, as mean square [nm²] (signed).
double removed_ms(const FamilyScore& s) { return s.removed_nm * std::fabs(s.removed_nm); }

const std::string* signal_of(const FamilyScore& s) {
  const auto it = s.best.labels.find("signal");
  return it == s.best.labels.end() ? nullptr : &it->second;
}

}  // namespace

const char* rule_name(AcceptanceRule rule) {
  switch (rule) {
    case AcceptanceRule::kSignificance: return "significance";
    case AcceptanceRule::kSize: return "size";
    case AcceptanceRule::kClearlyBetter: return "clearly better";
    case AcceptanceRule::kHoldGuard: return "hold guard";
    case AcceptanceRule::kHalves: return "halves";
    case AcceptanceRule::kGainVsAdditive: return "gain vs additive";
    case AcceptanceRule::kOperatingPoint: return "operating point";
  }
  return "?";
}

bool blocks_prefer(const std::vector<double>& a, const std::vector<double>& b) {
  const std::size_t k = std::min(a.size(), b.size());
  double mean = 0.0;
  for (std::size_t j = 0; j < k; ++j) mean += (a[j] - b[j]) / static_cast<double>(k);
  // Under four blocks the paired test has no power: the lower mean decides, as a plain validation choice.
  if (k < 4) return k > 0 && mean < 0.0;
  double var = 0.0;
  for (std::size_t j = 0; j < k; ++j) var += (a[j] - b[j] - mean) * (a[j] - b[j] - mean) / static_cast<double>(k - 1);
  return mean < -2.0 * std::sqrt(var / static_cast<double>(k));
}

Verdict rule_significance(const FamilyScore& s, const AcceptanceThresholds& t) {
  const AcceptanceRule r = AcceptanceRule::kSignificance;
  if (!s.available) return refuse(r, "not available: " + s.note);
  if (s.p_value >= t.alpha) return refuse(r, "not significant (p " + std::to_string(s.p_value) + ")");
  if (s.explained_variance < t.min_explained_variance)
    return refuse(r, "explains under " + pct(t.min_explained_variance) + " of the residual variance");
  return pass(r);
}

Verdict rule_size(const FamilyScore& s, const AcceptanceThresholds& t, const AcceptanceRound& round) {
  const AcceptanceRule r = AcceptanceRule::kSize;
  const double sigma = round.noise_sigma_nm;
  if (sigma > 0) {
    const double explained = std::sqrt(std::max(0.0, s.explained_variance) *
                                       (sigma * sigma + round.systematic_nm * round.systematic_nm));
    if (explained < t.min_explained_noise * sigma)
      return refuse(r, "explains " + nm(explained) + " of the residual in cross-validation, under " +
                           nm(t.min_explained_noise * sigma) + " (" +
                           std::to_string(t.min_explained_noise).substr(0, 4) + " σ of the reading noise)");
  }
  const double need = line_in_time(s) ? t.time_trend_min_removed_fraction : t.min_removed_fraction;
  if (s.removed_fraction < need)
    return refuse(r, "removes " + pct(s.removed_fraction) + " of the validation systematic error (" +
                         nm(round.systematic_nm) + "), needs " + pct(need));
  const double floor = t.min_removed_noise * round.block_noise_nm;
  if (s.removed_nm < floor)
    return refuse(r, "removes " + nm(s.removed_nm) + " of systematic error, within the noise of a 30-s mean (" + nm(floor) + ")");
  return pass(r);
}

Verdict rule_clearly_better(const FamilyScore& s, const AcceptanceThresholds& t) {
  const AcceptanceRule r = AcceptanceRule::kClearlyBetter;
  if (!s.clearly_better && s.removed_fraction < t.clear_size_fraction)
    return refuse(r, "removes " + pct(s.removed_fraction) + " of the systematic error and is not clearly better than "
                     "without it (paired blocks)");
  return pass(r);
}

Verdict rule_hold_guard(const FamilyScore& s, const AcceptanceThresholds& t, const AcceptanceRound& round) {
  const AcceptanceRule r = AcceptanceRule::kHoldGuard;
  if (round.validation_has_holds && s.hold_validation_gain < -t.hold_tolerance)
    return refuse(r, "worsens the validation error inside holds");
  return pass(r);
}

// Slow structure the base misses (creep modes longer than the fit part, a slow thermal wander) lets a trend or
// slow term fitted on the fit part win just after it and lose further on: a real effect keeps helping in both
// halves of the validation part. Except for lines in time, which extrapolate, a half counts only when clearly
// worse there, so a real effect that loses a half within its noise is not refused.
Verdict rule_halves(const FamilyScore& s, const AcceptanceThresholds& t) {
  const AcceptanceRule r = AcceptanceRule::kHalves;
  const double worst = std::min(s.validation_gain_halves.first, s.validation_gain_halves.second);
  if (worst < -t.half_tolerance && (line_in_time(s) || s.half_clearly_worse))
    return refuse(r, "does not generalise in time: worsens one half of the validation part");
  return pass(r);
}

Verdict rule_gain_vs_additive(const FamilyScore& gain, const FamilyScore& additive, const AcceptanceThresholds& t) {
  const AcceptanceRule r = AcceptanceRule::kGainVsAdditive;
  const bool clearly = blocks_prefer(gain.block_mae, additive.block_mae);
  const bool margin = removed_ms(gain) >= t.gain_margin * removed_ms(additive);
  if (clearly && margin) return pass(r);
  return refuse(r, "a gain that did not beat the additive " + additive.family + " on the same signal (systematic error removed " +
                       pct(gain.removed_fraction) + " vs " + pct(additive.removed_fraction) +
                       (clearly ? "" : ", not clearly better by paired blocks") + ")");
}

Verdict rule_operating_point(const FamilyScore& op, const FamilyScore& physical, const AcceptanceThresholds& t) {
  const AcceptanceRule r = AcceptanceRule::kOperatingPoint;
  const bool clearly = blocks_prefer(op.block_mae, physical.block_mae);
  const bool margin = removed_ms(op) >= t.operating_point_margin * removed_ms(physical);
  if (clearly && margin) return pass(r);
  return refuse(r, "depends on the operating point and did not beat " + physical.family + " by the margin (systematic error removed " +
                       pct(op.removed_fraction) + " vs " + pct(physical.removed_fraction) +
                       (clearly ? "" : ", not clearly better by paired blocks") + ")");
}

Verdict judge_alone(const FamilyScore& s, const AcceptanceThresholds& t, const AcceptanceRound& round) {
  for (const Verdict& v : {rule_significance(s, t), rule_size(s, t, round), rule_clearly_better(s, t),
                           rule_hold_guard(s, t, round), rule_halves(s, t)})
    if (!v.pass) return v;
  return pass(AcceptanceRule::kHalves);
}

namespace {

std::string labelled(const Verdict& v) { return std::string(rule_name(v.rule)) + ": " + v.reason; }

// A gain against the additive family on the same signal, when that one passed its own rules.
void gains_against_additives(std::vector<FamilyScore>& ranking, const std::vector<char>& ok, const AcceptanceThresholds& t,
                             std::vector<char>& out) {
  for (std::size_t i = 0; i < ranking.size(); ++i) {
    if (!ok[i] || !is_gain_family(ranking[i].family)) continue;
    const FamilyTraits& tr = traits_of(ranking[i].family);
    for (std::size_t j = 0; j < ranking.size(); ++j) {
      if (!ok[j] || ranking[j].family != traits(*tr.additive).name) continue;
      const std::string *sg = signal_of(ranking[i]), *sa = signal_of(ranking[j]);
      if (tr.compares_signal && (!sg || !sa || *sg != *sa)) continue;
      const Verdict v = rule_gain_vs_additive(ranking[i], ranking[j], t);
      if (!v.pass) ranking[i].verdict = labelled(v), out[i] = 0;
    }
  }
}

// The best (most systematic error removed) eligible family of one kind, -1 if none.
int best_of(const std::vector<FamilyScore>& ranking, const std::vector<char>& ok, bool operating_point) {
  int best = -1;
  for (std::size_t i = 0; i < ranking.size(); ++i) {
    if (!ok[i] || is_operating_point_family(ranking[i].family) != operating_point) continue;
    if (best < 0 || ranking[i].removed_fraction > ranking[static_cast<std::size_t>(best)].removed_fraction)
      best = static_cast<int>(i);
  }
  return best;
}

}  // namespace

int choose_effect(std::vector<FamilyScore>& ranking, const AcceptanceThresholds& t, const AcceptanceRound& round,
                  std::vector<FamilyScore>* competitors) {
  std::vector<char> ok(ranking.size(), 0);
  for (std::size_t i = 0; i < ranking.size(); ++i) {
    const Verdict v = judge_alone(ranking[i], t, round);
    ok[i] = v.pass;
    if (!v.pass && ranking[i].available) ranking[i].verdict = labelled(v);
  }
  std::vector<char> eligible = ok;
  gains_against_additives(ranking, ok, t, eligible);
  const int phys = best_of(ranking, eligible, false), op = best_of(ranking, eligible, true);
  int winner = phys;
  std::string op_refusal;
  if (op >= 0) {
    const Verdict v = phys >= 0 ? rule_operating_point(ranking[static_cast<std::size_t>(op)],
                                                       ranking[static_cast<std::size_t>(phys)], t)
                                : pass(AcceptanceRule::kOperatingPoint);
    if (v.pass) winner = op;
    else op_refusal = labelled(v);
  }
  if (winner < 0) return -1;
  FamilyScore& w = ranking[static_cast<std::size_t>(winner)];
  for (std::size_t i = 0; i < ranking.size(); ++i) {
    if (static_cast<int>(i) == winner || !eligible[i]) continue;
    FamilyScore& s = ranking[i];
    if (static_cast<int>(i) == op && !op_refusal.empty()) s.verdict = op_refusal;
    else s.verdict = "removes less systematic error than " + w.family + ": " + pct(s.removed_fraction) + " vs " +
                     pct(w.removed_fraction);
    if (competitors) competitors->push_back(s);
  }
  w.verdict = "kept";
  return winner;
}

}  // namespace piezo::analysis
