// Subnormal numbers (|x| < 2.2e-308) flushed to zero on the calling thread while a guard lives.
//
// Creep filters decay geometrically: a filter state whose input has gone to zero (a Preisach piece outside its knot
// range, a decayed initial state) passes through the subnormal range on its way to zero, and there every multiply
// is a microcode assist of ~100 cycles: in fit_pi_creep's per-piece filter bank, most of a Preisach fit's time. A
// value that small is zero for any position in nanometres, so flushing it changes no result that means anything.
//
// The guard sets FTZ and DAZ in MXCSR (x86 SSE/AVX) and restores the previous mode when it goes out of scope, so
// nesting is fine and the caller's mode is never changed; elsewhere it does nothing.
#pragma once

namespace piezo::util {

class FlushSubnormals {
 public:
  FlushSubnormals();
  ~FlushSubnormals();
  FlushSubnormals(const FlushSubnormals&) = delete;
  FlushSubnormals& operator=(const FlushSubnormals&) = delete;

 private:
  unsigned saved_ = 0;
};

}  // namespace piezo::util
