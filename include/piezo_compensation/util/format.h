// A number as text for messages and reports: `digits` significant digits, the stream's default notation (as
// printf's %g), e.g. fmt(1830.17, 4) = "1830", fmt(0.12185, 5) = "0.12185".
#pragma once

#include <string>

namespace piezo::util {

std::string fmt(double x, int digits);

}  // namespace piezo::util
