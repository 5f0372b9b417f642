// The PI and Preisach fits' options (private to training/pi): read from the fit's option map and checked once, each
// range check naming its option.
#pragma once

#include <yaml-cpp/yaml.h>

#include <string>
#include <vector>

#include "piezo_compensation/models/creep_models.h"

namespace piezo::training::pi {

// Options of fit_pi_creep.
struct PiFitOptions {
  bool initial_state_terms = true;
  double min_slope_fraction = 0.01;  // smallest initial slope, as a fraction of the overall V→position slope
  bool joint_on_h = false;           // creep_on_h_fit: joint (else alternate)
  int joint_iterations = 12;
  int alternations = 6, final_alternations = 6;
  std::string creep_input;           // voltage, hysteresis or auto
  int knots_per_span = 0;            // 0: the number of play operators, at most 12
  std::string input_map = "off";     // PI kinds: off, on, or auto (by validation)
  double piece_smoothing = 0.1;
  bool thresholds_given = false, n_play_given = false;
  std::vector<double> thresholds_v;
  int n_play = 12;
  std::string hold_weight;           // auto, off or a factor
  double hold_weight_factor = 1.0;
  bool refit_with_validation = false;
  // The creep law: grid, starting values and what is searched.
  int decades = 5, modes_per_decade = 2;
  double tau_min_s = 1.0, tau_max_s = 1.0, t1_s = 1.0, alpha = 0.5;
  bool t1_given = false, alpha_given = false, taus_given = false, fix_taus = false;
  bool warm_start = false;  // the given law (taus_s, t1_s or alpha) is a start, refined near it (refit_options)
  std::vector<double> taus_s;
  int n_pairs = 2, search_rounds = 3;
};

// The options of a fit of creep law `kind` (the preisach kinds when `preisach`); tau_lo/tau_hi: the time constants
// the training data can identify (the creep law's defaults). Throws std::runtime_error naming a bad option.
PiFitOptions parse_pi_options(const YAML::Node& o, models::CreepKind kind, bool preisach, bool has_validation,
                              double tau_lo, double tau_hi);

}  // namespace piezo::training::pi
