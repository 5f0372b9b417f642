// `--model auto` is stable under the effects the residual loop must find: on the package's own simulated stage with
// one effect planted (each family of the loop: encoder periodic error, coupling from axis a, a temperature signal, a
// temperature-driven stroke gain), it chooses the kind it chooses on the same stage without the effect, or one within
// the noise of that choice on the clean stage. Its candidates read only the axis's own voltage, so the effect stays
// in the residual for the loop.
#include <gtest/gtest.h>

#include <cstdio>

#include "piezo_compensation/analysis/selection/model_selection.h"
#include "piezo_compensation/analysis/residual/residual_sensitivity.h"

using namespace piezo;

namespace {

constexpr double kHours = 1.0;
constexpr double kSizeSigma = 1.5;  // each effect's RMS on the readings over the reading noise
constexpr std::uint64_t kSeed = 5151;

// auto on TRAIN (the stage's first two thirds), as `piezo residual --model auto` runs it: the fit part the first
// 75 %, the rest validates.
analysis::Selection choose(const io::Dataset& stage) {
  const io::Dataset train = stage.slice(0, stage.size() * 2 / 3);
  const std::size_t n_fit = train.size() * 3 / 4;
  const io::Dataset fit = train.slice(0, n_fit), val = train.slice(n_fit, train.size());
  analysis::SelectionRequest rq = analysis::selection_request(fit, &val, train, n_fit, "c");
  rq.identify = false;
  return analysis::select_model(rq);
}

const analysis::CandidateResult* row(const analysis::Selection& s, const std::string& label) {
  for (const auto& r : s.table)
    if (r.candidate.label == label) return &r;
  return nullptr;
}

}  // namespace

TEST(AutoStability, APlantedEffectDoesNotChangeTheChoiceBeyondTheNoise) {
  const analysis::Selection clean = choose(analysis::sensitivity_stage(nullptr, 0.0, kHours, kSeed));
  const auto& chosen = clean.table[clean.best];
  std::printf("clean stage:\n%s\n", analysis::selection_table(clean).c_str());
  for (const auto f : {analysis::SensitivityFamily::kPeriodic, analysis::SensitivityFamily::kCrossAxis,
                       analysis::SensitivityFamily::kAuxSignal, analysis::SensitivityFamily::kGain}) {
    const analysis::Selection planted = choose(analysis::sensitivity_stage(&f, kSizeSigma, kHours, kSeed));
    const std::string label = planted.table[planted.best].candidate.label;
    const analysis::CandidateResult* on_clean = row(clean, label);
    ASSERT_NE(on_clean, nullptr) << label;
    std::vector<std::string> worse;
    const bool within = label == chosen.candidate.label ||
                        (on_clean->refused.empty() && analysis::within_noise(chosen.slow, on_clean->slow, &worse));
    std::printf("%s planted: chose %s (clean: %s)%s\n", analysis::sensitivity_family_name(f), label.c_str(),
                chosen.candidate.label.c_str(), within ? "" : "; clearly worse on the clean stage");
    EXPECT_TRUE(within) << analysis::sensitivity_family_name(f) << ": chose " << label << "; on the clean stage it is "
                        << "clearly worse than " << chosen.candidate.label << " on " << (worse.empty() ? "?" : worse[0])
                        << "\n" << analysis::selection_table(planted);
  }
}

