// Backfitting after an effect is added: the base is refitted on TRAIN with the effect terms' part taken out,
// then the terms on the refitted base's residual, a few rounds, so a base that absorbed part of the effect when
// first fitted gives it back. The effect's variant (lag, low-pass, form) is chosen again on each refitted base.
#pragma once

#include <random>
#include <utility>
#include <vector>

#include "piezo_compensation/analysis/residual/residual_validation.h"

namespace piezo::analysis::detail {

class Backfitter {
 public:
  Backfitter(Context& c, const Validator& v, const ResidualOptions& o, const io::Dataset& train, std::mt19937_64& rng);

  // `winner` was just added as terms[first, end) and all terms fitted on TRAIN; refits base and terms in turn
  // (ResidualOptions::backfit_iterations, gain_backfit_iterations). Updates c.x_base, base, terms, level and the
  // winner's best variant.
  void run(FamilyScore& winner, std::vector<models::EffectTerm>& terms, std::size_t first, Level& level,
           models::ModelPtr& base);
  // One more refit of the base with every term's part taken out, then the terms on its residual (the loop's last
  // step, after each effect's variant was chosen again given the others). No-op without ResidualOptions::refit_base.
  void refit_all(std::vector<models::EffectTerm>& terms, Level& level, models::ModelPtr& base);
  // The base refitted once on TRAIN with `terms`' part taken out (c.x_base follows), then `terms` on its residual.
  void refit_without(std::vector<models::EffectTerm>& terms, Level& level, models::ModelPtr& base);
  // terms[q]'s lag as a first-order low-pass, profiled over τ (0 and 10 s … tau_max_s) with the base refitted for
  // each τ (same structure) and all terms refitted jointly on TRAIN; the best τ's terms, level and base are kept
  // (c.x_base follows). Returns (τ [s], TRAIN RMS [nm]) for every τ tried. Without refit_base the base stays.
  LagProfile profile_lag(std::vector<models::EffectTerm>& terms, std::size_t q, Level& level, models::ModelPtr& base,
                         double tau_max_s);

 private:
  // The secant on the size of a gain fitted after each refit (see the .cpp); how many times its part is taken out.
  struct Secant {
    double point_a = 0.0, point_f = 0.0, removed_last = 0.0;
    bool plain_step = false;  // the next refit takes the effect out once (a new form: the points are another's)
  };
  double gain_kappa(int it, const std::vector<double>& part, Secant& s) const;
  std::vector<double> effect_part(const std::vector<models::EffectTerm>& terms, std::size_t first, const Level& level) const;
  void refit_once(const std::vector<models::EffectTerm>& terms, const Level& level, const std::vector<double>& part,
                  double kappa, models::ModelPtr& base, bool same_structure = false);
  struct LagTrial {
    std::vector<models::EffectTerm> terms;
    Level level;
    models::ModelPtr base;
    std::vector<double> x_base;
    std::vector<double> validation_sq;  // squared errors on the validation part, the terms fitted on the fit part
    double rms_nm = 0.0;
  };
  LagTrial lag_trial(const std::vector<models::EffectTerm>& terms, std::size_t q, const models::Model& base, double tau_s);
  // Chooses the winner's variant again on the refitted base; true when the gain's form changed at the last refit.
  bool choose_again(FamilyScore& winner, std::vector<models::EffectTerm>& terms, std::size_t first, Level& level,
                    bool last);

  Context& c_;
  const Validator& v_;
  const ResidualOptions& o_;
  const io::Dataset& train_;
  std::mt19937_64& rng_;
  bool form_after_refits_ = false;
};

}  // namespace piezo::analysis::detail
