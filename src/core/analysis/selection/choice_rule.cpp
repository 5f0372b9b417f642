// The `--model auto` choice among scored candidates: within the noise of the best (a paired test per column), the
// fewest parameters (analysis/selection/model_selection.h: choose_candidate).
#include "piezo_compensation/analysis/selection/model_selection.h"

#include <cmath>
#include <sstream>

#include "piezo_compensation/training/fit_common.h"
#include "piezo_compensation/util/format.h"

namespace piezo::analysis {

namespace {
struct Column {
  const char* name;
  const std::vector<double> SlowErrors::*v;
  double SlowScore::*mean;
};
const Column kColumns[] = {{"10-s moves", &SlowErrors::move_short, &SlowScore::move_short_nm},
                           {"60-s moves", &SlowErrors::move_long, &SlowScore::move_long_nm},
                           {"hold creep", &SlowErrors::hold_creep, &SlowScore::hold_creep_nm}};
}  // namespace

bool within_noise(const SlowScore& best, const SlowScore& other, std::vector<std::string>* worse) {
  bool within = true;
  for (const auto& c : kColumns) {
    const auto& a = best.blocks.*c.v;
    const auto& b = other.blocks.*c.v;
    if (a.empty() || b.empty()) continue;
    const std::size_t block = std::max(best.block, std::size_t{1});
    if ((other.*c.mean) - (best.*c.mean) > best.noise_nm && training::validation_prefers(a, b, block)) {
      within = false;
      if (worse) worse->push_back(c.name);
    }
  }
  return within;
}

namespace {
std::string nm(double x) { return std::isfinite(x) ? util::fmt(x, 3) + " nm" : std::string("–"); }

// Why the chosen candidate (the lowest overall) is not one with fewer parameters: the best of those, and the columns
// on which it is clearly worse.
std::string why_not_simpler(const std::vector<ChoiceEntry>& en, std::size_t chosen) {
  const ChoiceEntry& c = en[chosen];
  std::size_t s = SIZE_MAX;
  for (std::size_t k = 0; k < en.size(); ++k)
    if (en[k].score && en[k].score->valid() && en[k].parameters < c.parameters &&
        (s == SIZE_MAX || en[k].score->overall_nm < en[s].score->overall_nm))
      s = k;
  if (s == SIZE_MAX) return "; no candidate has fewer parameters";
  std::vector<std::string> worse;
  within_noise(*c.score, *en[s].score, &worse);
  std::ostringstream r;
  r << "; " << en[s].label << " (" << en[s].parameters << " parameters) is clearly worse on";
  for (std::size_t i = 0; i < worse.size(); ++i) {
    double v = NAN, mine = NAN;
    for (const auto& col : kColumns)
      if (worse[i] == col.name) v = (*en[s].score).*col.mean, mine = (*c.score).*col.mean;
    r << (i ? "," : "") << " " << worse[i] << " (" << nm(v) << " vs " << nm(mine) << ")";
  }
  return r.str();
}
}  // namespace

Choice choose_candidate(const std::vector<ChoiceEntry>& en) {
  Choice ch;
  for (std::size_t k = 0; k < en.size(); ++k)
    if (en[k].score && en[k].score->valid() &&
        (ch.best_overall == SIZE_MAX || en[k].score->overall_nm < en[ch.best_overall].score->overall_nm))
      ch.best_overall = k;
  if (ch.best_overall == SIZE_MAX) return ch;
  const ChoiceEntry& b = en[ch.best_overall];
  ch.chosen = ch.best_overall;
  for (std::size_t k = 0; k < en.size(); ++k) {
    if (k == ch.best_overall || !en[k].score || !en[k].score->valid()) continue;
    const ChoiceEntry& c = en[k];
    const ChoiceEntry& cur = en[ch.chosen];
    const bool simpler = c.parameters < cur.parameters ||
                         (c.parameters == cur.parameters && c.score->overall_nm < cur.score->overall_nm);
    if (simpler && within_noise(*b.score, *c.score)) ch.chosen = k;
  }
  const ChoiceEntry& c = en[ch.chosen];
  std::ostringstream r;
  if (ch.chosen != ch.best_overall)
    r << c.label << ": within the noise of " << b.label << " (lowest overall " << nm(b.score->overall_nm)
      << ") on every column, overall " << nm(c.score->overall_nm) << ", with " << c.parameters << " instead of "
      << b.parameters << " parameters";
  else
    r << c.label << ": lowest overall " << nm(c.score->overall_nm) << why_not_simpler(en, ch.chosen);
  ch.reason = r.str();
  return ch;
}

}  // namespace piezo::analysis
