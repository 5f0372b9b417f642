// Sensitivity of the residual loop: how often it names an effect of a given size, and how often it adds anything
// to a stage without one. A harness around trace_residual (analysis/residual/residual.h), which itself never reads
// simulator settings: here the simulator builds the stages, each effect planted at a size in units of the reading
// noise σ (the RMS of what it adds to the readings over σ), and the loop is run on them blind.
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "piezo_compensation/analysis/residual/residual.h"

namespace piezo::analysis {

// The families the harness plants, and the loop families that name each (detection = one of them is added).
enum class SensitivityFamily { kPeriodic, kCrossAxis, kAuxSignal, kGain };
const char* sensitivity_family_name(SensitivityFamily f);
// Parses "periodic", "cross_axis", "aux_signal", "gain"; throws std::invalid_argument listing the valid names.
SensitivityFamily parse_sensitivity_family(const std::string& name);

struct SensitivityOptions {
  // The stage: the simulator's default axes a and c, a random walk on both, `hours` long, TRAIN the first
  // `train_fraction`, a temperature_c column on every stage (a slow sine + random walk, felt only when planted).
  double hours = 6.0;
  double train_fraction = 2.0 / 3.0;
  std::string base_kind = "pi_creep_lti";  // fitted on TRAIN's fit part, refitted while the loop backfits
  std::vector<SensitivityFamily> families{SensitivityFamily::kPeriodic, SensitivityFamily::kCrossAxis,
                                          SensitivityFamily::kAuxSignal, SensitivityFamily::kGain};
  std::vector<double> sizes_sigma{0.25, 0.5, 1.0, 1.5, 2.0};  // effect RMS over the reading noise σ
  int trials = 5;         // stages per (family, size)
  int clean_trials = 20;  // stages without an effect
  std::uint64_t seed = 1000;  // trial t uses seed + t (the same stages for every family and size)
  int permutations = 20;      // circular-shift draws per family in the loop
  std::function<void(const std::string&)> progress;  // one line per trial (may be empty)
  std::function<void(const std::string&)> loop_log;  // the loop's own progress lines (may be empty)
};

struct SensitivityCell {
  SensitivityFamily family = SensitivityFamily::kPeriodic;
  double size_sigma = 0.0;
  int trials = 0;
  int detected = 0;  // the planted family named
  int other = 0;     // something else added, the planted family not named
};

struct SensitivityResult {
  double noise_sigma_nm = 0.0;  // the reading noise the sizes are in units of (the simulator's c encoder)
  std::vector<SensitivityCell> cells;
  int clean_trials = 0;
  int clean_false = 0;                  // clean stages where anything was added
  std::vector<std::string> clean_added; // what was added there, one entry per effect
  double seconds = 0.0;                 // wall time
};

SensitivityResult run_sensitivity(const SensitivityOptions& o);

// One of the harness's stages: `family` planted on c at size_sigma (null: clean), `hours` long, the seed's random
// walk and temperature; *sigma_nm (optional) receives c's reading noise.
io::Dataset sensitivity_stage(const SensitivityFamily* family, double size_sigma, double hours, std::uint64_t seed,
                              double* sigma_nm = nullptr);

// A markdown table: one row per family, one column per size (detected / trials), then the clean stages'
// false-positive rate, and the options that reproduce it.
std::string sensitivity_table(const SensitivityResult& r, const SensitivityOptions& o);

// A stage with effects against the same stage without them: the figure the residual loop is judged by (its TEST
// error against the truth after the loop over that of the clean stage after the loop).
struct ComparisonOptions {
  // A stage file (config/stages/*.yaml) whose axis c is the one modelled; axis a is driven too, with c's physics
  // and encoder_step_a_nm steps (the instrument's coarse axes). Empty: the simulator's default axes a and c.
  std::string stage_path;
  double encoder_step_a_nm = 250.0;
  double hours = 6.0;                 // random-walk stages; a creep-protocol stage is truncated to it
  double train_fraction = 2.0 / 3.0;
  std::string base_kind = "pi_creep_lti";
  // Planted on c: "cross_axis" (a's displacement, through its position: sim effect cross_axis), "gain" (c's stroke
  // scaled by 1 + g·(temperature through a first-order lag of gain_lag_s − 22 °C)), "periodic" (the encoder's
  // interpolation error), "slips" (the mount slips +60 nm and −45 nm at 80 % and 90 % of the stage). Sizes: each
  // effect's RMS on the readings over the reading noise σ (slips: fixed).
  std::vector<std::string> effects;
  double size_sigma = 1.5;
  double gain_lag_s = 90.0;
  // The room's temperature is a 2-h cycle of 0.9 °C and a slow random walk; this adds a Gauss–Markov wander of
  // this SD [°C] with a 400-s correlation time: content on the time scale of the lag, which the cycle lacks.
  double temperature_wander_c = 0.0;
  // Axis a's model (the base kind fitted on a, its estimator identified on TRAIN's validation part) gives the loop
  // a's fused position (add_fused_positions); false: a enters through its readings and voltage only.
  bool fused_other_axis = true;
  std::uint64_t seed = 4000;
  int permutations = 20;
  std::function<void(const std::string&)> loop_log;
};

struct ComparisonRun {
  double before_truth_nm = 0.0, after_truth_nm = 0.0;  // TEST MAE of the stage position against the truth
  std::vector<FoundEffect> effects;
};
struct ComparisonResult {
  ComparisonRun with_effects, clean;
  double noise_sigma_nm = 0.0;
  double seconds = 0.0;
};

ComparisonResult run_comparison(const ComparisonOptions& o);
// Markdown: both runs, what was named (with its parameters and where it acts), the ratio, the options.
std::string comparison_text(const ComparisonResult& r, const ComparisonOptions& o);

}  // namespace piezo::analysis
