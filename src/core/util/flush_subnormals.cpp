#include "piezo_compensation/util/flush_subnormals.h"

#if defined(__SSE__) || defined(__x86_64__)
#include <xmmintrin.h>
#define PIEZO_HAVE_MXCSR 1
#endif

namespace piezo::util {

namespace {
#ifdef PIEZO_HAVE_MXCSR
constexpr unsigned kFlushToZero = 0x8000;      // results that would be subnormal become 0
constexpr unsigned kDenormalsAreZero = 0x0040; // subnormal inputs are read as 0
#endif
}  // namespace

FlushSubnormals::FlushSubnormals() {
#ifdef PIEZO_HAVE_MXCSR
  saved_ = _mm_getcsr();
  _mm_setcsr(saved_ | kFlushToZero | kDenormalsAreZero);
#endif
}

FlushSubnormals::~FlushSubnormals() {
#ifdef PIEZO_HAVE_MXCSR
  _mm_setcsr(saved_);
#endif
}

}  // namespace piezo::util
