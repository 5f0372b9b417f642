#include "piezo_compensation/util/format.h"

#include <sstream>

namespace piezo::util {

std::string fmt(double x, int digits) {
  std::ostringstream s;
  s.precision(digits);
  s << x;
  return s.str();
}

}  // namespace piezo::util
