// Validation of effect terms in the residual loop: terms fitted on TRAIN's first part, scored on the rest
// (overall, inside holds, in both halves, per paired block), and a family's best variant refined there (a gain's
// form, a low-pass's τ). Fills the FamilyScore fields the acceptance rules read (analysis/residual/residual_acceptance.h).
#pragma once

#include <cstddef>
#include <functional>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/residual/residual_context.h"

namespace piezo::analysis::detail {

// Validation errors of one set of terms.
struct Val {
  double mae = 0, mse = 0, hold_mae = 0, mae1 = 0, mae2 = 0;
  std::vector<double> abs_err;  // per validation sample, for paired comparisons
};

class Validator {
 public:
  Validator(const Context& c, std::size_t n_fit, const AcceptanceThresholds& t, std::function<void(const std::string&)> log);

  // Terms (unfitted) fitted on rows [0, n_fit), scored on [n_fit, n).
  Val validate(std::vector<models::EffectTerm> terms) const;
  // Validates `fixed` plus the family's best variant against `now` (fixed alone) and fills the score's validation
  // fields; with choose_form a gain's form (on the output or the voltage, linear or quadratic) is chosen here.
  // Its low-pass time constants are refined on the fit part only: the validation rows judge them.
  void score(FamilyScore& s, const std::vector<models::EffectTerm>& fixed, const Val& now, bool choose_form) const;
  // An accepted effect's time constants refined again over all of TRAIN (more rows: τ not chosen on the noise),
  // within a factor √2 of the validated ones and never past half the validation part.
  void finalise_time_constants(FamilyScore& s, const std::vector<models::EffectTerm>& fixed) const;
  // What the acceptance rules know of the round with `now` as the model without a new effect.
  AcceptanceRound round(const Val& now) const;
  // |error| per paired block (one value, the mean, when there are under four blocks).
  std::vector<double> block_mae(const std::vector<double>& abs_err) const;

  std::size_t n_fit() const { return n_fit_; }
  std::size_t paired_block() const { return paired_block_; }
  // The longest low-pass time constant the validation rows can judge: half the validation part [s].
  double max_time_constant_s() const { return 0.5 * static_cast<double>(n_ - n_fit_) / c_.fs; }
  bool has_holds() const { return n_val_hold_ > 0; }

 private:
  void prefer_fused_position(FamilyScore& s, const std::vector<models::EffectTerm>& fixed, Val& v) const;
  void choose_gain_form(FamilyScore& s, const std::vector<models::EffectTerm>& fixed, Val& v) const;
  bool refine_time_constants(FamilyScore& s, const std::vector<models::EffectTerm>& fixed, std::size_t rows,
                             double span) const;
  bool split_delay(FamilyScore& s, const std::vector<models::EffectTerm>& fixed, std::size_t rows, std::size_t q) const;
  double train_ms(const std::vector<models::EffectTerm>& fixed, const Candidate& cand, std::size_t rows) const;
  void fill_sizes(FamilyScore& s, const Val& v, const Val& now) const;
  void log_score(const FamilyScore& s) const;

  const Context& c_;
  std::size_t n_fit_, n_;
  const AcceptanceThresholds& t_;
  std::function<void(const std::string&)> log_;
  std::vector<char> holds_;
  std::size_t n_val_hold_ = 0;
  std::size_t paired_block_ = 1;
};

}  // namespace piezo::analysis::detail
