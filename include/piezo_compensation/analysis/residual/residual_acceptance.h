// The residual loop's acceptance policy: named rules applied in order to every family scored in a round, each
// returning a verdict with its reason, and the choice of the one effect added. Pure functions of the scores
// (FamilyScore, analysis/residual/residual.h): tested on hand-made score vectors (test_residual_acceptance).
//
// The size of an effect is judged against the measurement's own noise, not as a fixed share of the MAE. The
// validation error's mean square is the reading noise's σ² (estimated from the data, analysis/evaluation/noise_floor.h) plus
// the systematic error the model makes; a candidate must remove a real share of that systematic error, more than
// a 30-s average of the readings can resolve, and be clearly better over paired 5-min blocks. (Equivalently: its
// Gaussian log-likelihood gain with the estimated σ, n·ΔMSE/2σ², set against the model's own misfit.) A fixed
// 3 % of MAE refused a real 5 nm effect under 21 nm noise (≈ 1 % of the MAE) and would accept 3 % of noise on a
// quiet sensor.
#pragma once

#include <cstddef>
#include <string>
#include <vector>

namespace piezo::analysis {

struct FamilyScore;

// Every threshold of the residual loop's acceptance, each with why it has its value.
struct AcceptanceThresholds {
  // Significance of the family's cross-validated fit against circular-shift draws (or the red-noise periodogram):
  // the usual 1 %; with ~11 families a round, a false family passes this about once in ten rounds, and the
  // validation rules below are what stop it.
  double alpha = 0.01;
  // Cross-validated share of the residual variance: below 1 % the fit is too small to estimate a lag or form.
  double min_explained_variance = 0.01;
  // … and what that share is in nm, √(EV · (σ² + systematic²)) with the validation's systematic error, must be at
  // least this many σ of the reading noise: a slow signal (a temperature low-passed over minutes, a line in time)
  // correlates by chance with the slow misfit any base leaves, explaining 0.15–0.2 σ on clean simulated stages,
  // while an effect of 0.5 σ explains 0.3–0.5 σ there (docs/closing-the-loop.md, "Sensitivity").
  double min_explained_noise = 0.25;
  // Share of the validation systematic error (MSE − σ²) a candidate must remove: a smaller share is within what
  // refitting the same terms on another stretch moves by, and not worth a term that must also hold live.
  double min_removed_fraction = 0.10;
  // … for a line in time (time_drift, time_gain): its slope's error grows with the horizon past TRAIN, and a slow
  // wander of the base's creep misfit over a few hours looks like a line on the validation part. On the Preisach
  // gain stage such a line removes under half of what is left after the temperature gain (clearly better on
  // validation, yet worse against the truth in TEST), while a real drift of the stroke removes most of it
  // (docs/validation/residual-loop.md, step 4).
  double time_trend_min_removed_fraction = 0.65;
  // What it removes, √(ΔMSE) [nm], must exceed this many σ of a mean over resolution_block_s of readings: an
  // effect smaller than what a 30-s average resolves (21 nm noise at 11 Hz: 1.2 nm) is not measured, whatever
  // its share of a small misfit.
  double min_removed_noise = 1.0;
  double resolution_block_s = 30.0;
  // A candidate that removes at least this share of the systematic error is its own evidence; a smaller one must
  // also be clearly better over paired blocks. A large real effect need not help in every 5-min block (an
  // other-axis gain acts only where that axis is far from its mean: 51 % removed, not clearly better), while the
  // small ones are where noise and slow wander pass the size rule.
  double clear_size_fraction = 0.25;
  // Block of the paired tests [s] (training::validation_prefers, > 2 SE): the errors of a free run are
  // correlated over minutes, so paired samples would overstate the evidence.
  double paired_block_s = 300.0;
  // An effect may not raise the validation MAE inside holds by more than this share: holds are where a parked
  // tip must stay put; 0.5 % is below what one refit of the base moves it by.
  double hold_tolerance = 0.005;
  // … nor in either half of the validation part by more than this (it must generalise in time); for families
  // other than lines in time a half counts only when clearly worse there (paired blocks).
  double half_tolerance = 0.0;
  // A gain replaces the additive family on the same signal only when clearly better than it (paired blocks) and
  // removing ≥ this × the systematic error it removes: where the base output varies little the two are the same fit, and the
  // additive one extrapolates safely to other positions.
  double gain_margin = 1.2;
  // An operating-point family replaces the best physical-signal family only when clearly better than it and
  // removing ≥ this × the systematic error it removes: it can imitate almost anything that varies with the drive.
  double operating_point_margin = 1.5;
  // A quadratic gain form must cut the validation MAE by this share besides being clearly better than the
  // linear one (one parameter more, fitted to the same error).
  double quadratic_form_margin = 0.01;
};

// What the rules know of the round besides the scores.
struct AcceptanceRound {
  bool validation_has_holds = false;
  double block_noise_nm = 0.0;      // σ/√B: the noise of a mean over resolution_block_s of readings [nm]
  double systematic_nm = 0.0;       // systematic error of the validation part without a new effect, √(MSE − σ²) [nm]
  double noise_sigma_nm = 0.0;      // the reading noise σ estimated from the data [nm] (0: the rule on it is off)
  std::vector<double> block_mae;    // validation |error| per paired block without a new effect
};

enum class AcceptanceRule {
  kSignificance,
  kSize,
  kClearlyBetter,
  kHoldGuard,
  kHalves,
  kGainVsAdditive,
  kOperatingPoint,
};
const char* rule_name(AcceptanceRule rule);

struct Verdict {
  bool pass = true;
  AcceptanceRule rule = AcceptanceRule::kSignificance;
  std::string reason;  // empty when passed
};

// The rules, one candidate at a time (those on two candidates take the one it must beat).
Verdict rule_significance(const FamilyScore& s, const AcceptanceThresholds& t);
Verdict rule_size(const FamilyScore& s, const AcceptanceThresholds& t, const AcceptanceRound& round);
Verdict rule_clearly_better(const FamilyScore& s, const AcceptanceThresholds& t);
Verdict rule_hold_guard(const FamilyScore& s, const AcceptanceThresholds& t, const AcceptanceRound& round);
Verdict rule_halves(const FamilyScore& s, const AcceptanceThresholds& t);
Verdict rule_gain_vs_additive(const FamilyScore& gain, const FamilyScore& additive, const AcceptanceThresholds& t);
Verdict rule_operating_point(const FamilyScore& op, const FamilyScore& physical, const AcceptanceThresholds& t);

// The one-candidate rules in order; the first refusal is the verdict.
Verdict judge_alone(const FamilyScore& s, const AcceptanceThresholds& t, const AcceptanceRound& round);

// Applies every rule to the round's ranking, writes each family's verdict ("kept", or the first rule that refused
// it with its reason, or why it lost to the winner) and returns the winner's index, or -1 when none passes.
// `competitors` receives the families that passed their own rules but lost to the winner.
int choose_effect(std::vector<FamilyScore>& ranking, const AcceptanceThresholds& t, const AcceptanceRound& round,
                  std::vector<FamilyScore>* competitors = nullptr);

// Paired-block comparison of two block-mean error vectors (one value per block, same blocks): a clearly lower
// than b (training::validation_prefers with block 1).
bool blocks_prefer(const std::vector<double>& a, const std::vector<double>& b);

}  // namespace piezo::analysis
