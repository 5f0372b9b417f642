// Mount slips: steps of the offset that no family explains. On the synthetic plant of
// test_residual_common.h without a planted effect, the tip slips twice in TEST. Nothing may be added, what is
// left is "not explained", and the slips are reported as steps within 60 s of their times with their sizes.
// (A slip inside TRAIN's fit part is another matter: a slow family such as missing_memory, τ ~ 4000 s, fits the
// step there and is added; docs/closing-the-loop.md, "Steps".)
#include <gtest/gtest.h>

#include <cstdlib>
#include <iostream>

#include "piezo_compensation/analysis/residual/residual.h"
#include "test_residual_common.h"

namespace pa = piezo::analysis;

TEST(ResidualSteps, MountSlipsAreReportedNotAdded) {
  piezo::io::Dataset d = piezo::test::synthetic(piezo::test::Planted::kNone, 3.0, 26);
  const std::size_t n_train = d.size() * 2 / 3;
  const double t_test = d.time_s[n_train];
  struct Slip {
    double time_s, size_nm;
  };
  const std::vector<Slip> slips = {{t_test + 1200.0, 60.0}, {t_test + 2700.0, -45.0}};
  auto& c = d.axis("c");
  for (std::size_t i = 0; i < d.size(); ++i)
    for (const Slip& s : slips)
      if (d.time_s[i] >= s.time_s) c.position_nm[i] += s.size_nm, c.true_position_nm[i] += s.size_nm;
  const piezo::io::Dataset train = d.slice(0, n_train), test = d.slice(n_train, d.size());
  pa::ResidualOptions o;
  o.axis = "c";
  if (std::getenv("PIEZO_RESIDUAL_VERBOSE")) o.log = [](const std::string& s) { std::cerr << s << "\n"; };
  const std::size_t n_fit = static_cast<std::size_t>(static_cast<double>(n_train) * (1.0 - o.validation_fraction));
  auto base = piezo::test::LowpassLinearModel::fit(train, "c", n_fit);
  const pa::ResidualResult r = pa::trace_residual(*base, train, test, o);
  std::cerr << "mount slips: " << pa::describe_remainder(r.remainder) << "\n";
  for (const auto& e : r.effects) ADD_FAILURE() << "added " << e.family;
  EXPECT_FALSE(r.remainder.explained);
  for (std::size_t k = 0; k < slips.size(); ++k) {
    bool found = false;
    for (const auto& st : r.remainder.steps)
      if (std::fabs(st.time_s - slips[k].time_s) <= 60.0 && std::fabs(st.size_nm - slips[k].size_nm) < 0.3 * std::fabs(slips[k].size_nm))
        found = true;
    EXPECT_TRUE(found) << "slip of " << slips[k].size_nm << " nm at t = " << slips[k].time_s << " s not reported";
  }
  EXPECT_LE(r.remainder.steps.size(), 3u) << "steps reported where there are none";
}
