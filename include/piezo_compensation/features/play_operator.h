// The play (backlash) operator, the one definition used by the play features, the PI models and their fits.
#pragma once

#include <algorithm>

namespace piezo::features {

// Output of a play operator of half-width r for input v, given its previous output.
inline double play(double v, double r, double prev) { return std::max(v - r, std::min(v + r, prev)); }

}  // namespace piezo::features
