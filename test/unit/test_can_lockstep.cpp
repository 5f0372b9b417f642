// Lock-step rules (can/lockstep.h): when the driver sends the next SYNC, and the ceiling on simulated time.
#include <gtest/gtest.h>

#include <stdexcept>

#include "piezo_compensation/can/lockstep.h"

using piezo::can::SyncGate;
using piezo::can::SyncPace;

namespace {
constexpr int kC = 2;
const std::array<bool, 3> kOnlyC{false, false, true};
const std::array<bool, 3> kAll{true, true, true};

// The device answers a SYNC with one reading per axis.
bool read_sample(SyncGate& g) {
  bool due = false;
  for (int axis = 0; axis < 3; ++axis) due = g.on_reading(axis) || due;
  return due;
}
}  // namespace

TEST(SyncGate, UnboundedSendsOnEveryCompleteSet) {
  SyncGate g(0);
  for (int i = 0; i < 5; ++i) {
    ASSERT_TRUE(g.on_command(kC, kOnlyC)) << i;
    g.synced(true);
  }
  EXPECT_EQ(g.in_flight(), 5);  // counted, never a reason to wait
  EXPECT_FALSE(g.waiting());
}

TEST(SyncGate, EveryCommandedAxisCompletesTheSet) {
  SyncGate g(2);
  EXPECT_FALSE(g.on_command(0, kAll));
  EXPECT_FALSE(g.on_command(2, kAll));
  EXPECT_FALSE(g.on_command(2, kAll)) << "a second command of one axis does not stand for another axis";
  EXPECT_TRUE(g.on_command(1, kAll));
  g.synced(true);
  EXPECT_FALSE(g.on_command(0, kAll)) << "the set starts again after a SYNC";
}

TEST(SyncGate, TwoCommandsPerSampleDoNotRunTheDeviceAhead) {
  // The predictor commands on the reading and on the intent: two complete sets per sample read. Unbounded that is
  // two SYNCs per sample consumed; with K = 2 the device is never more than 2 SYNCs ahead of the readings.
  SyncGate g(2);
  int syncs = 0, samples = 0, max_ahead = 0;
  for (int round = 0; round < 100; ++round) {
    for (int cmd = 0; cmd < 2; ++cmd)
      if (g.on_command(kC, kOnlyC)) {
        g.synced(true);
        ++syncs;
      }
    max_ahead = std::max(max_ahead, g.in_flight());
    if (g.in_flight() > 0) {
      ++samples;
      if (read_sample(g)) {  // the waiting set goes out with the reading
        g.synced(true);
        ++syncs;
      }
    }
  }
  EXPECT_LE(max_ahead, 2);
  EXPECT_LE(syncs, samples + 2);
  EXPECT_GE(syncs, samples);  // and it keeps going: every sample read releases the next
}

TEST(SyncGate, AWaitingSetGoesOutWithTheReadingThatBringsTheCountUnderTheBound) {
  SyncGate g(1);
  ASSERT_TRUE(g.on_command(kC, kOnlyC));
  g.synced(true);
  EXPECT_FALSE(g.on_command(kC, kOnlyC)) << "one SYNC is already without its reading";
  EXPECT_TRUE(g.waiting());
  EXPECT_TRUE(g.on_reading(0)) << "the first reading of the sample releases it";
  EXPECT_FALSE(g.on_reading(1)) << "the other axes' readings of the same sample count once";
  EXPECT_FALSE(g.on_reading(2));
  g.synced(true);
  EXPECT_FALSE(g.waiting());
  EXPECT_EQ(g.in_flight(), 1);
}

TEST(SyncGate, AnUnsentSyncIsNotInFlightAndIdleForgetsLostOnes) {
  SyncGate g(1);
  ASSERT_TRUE(g.on_command(kC, kOnlyC));
  g.synced(false);  // bus down
  EXPECT_EQ(g.in_flight(), 0);
  ASSERT_TRUE(g.on_command(kC, kOnlyC));
  g.synced(true);  // its sample is lost
  EXPECT_FALSE(g.on_command(kC, kOnlyC));
  EXPECT_TRUE(g.waiting());
  g.idle();  // the driver's idle SYNC: counting starts afresh with it, and it serves the waiting set
  g.synced(true);
  EXPECT_EQ(g.in_flight(), 1);
  EXPECT_FALSE(g.waiting());
  EXPECT_FALSE(g.on_reading(kC)) << "nothing waits";
  EXPECT_EQ(g.in_flight(), 0);
  EXPECT_TRUE(g.on_command(kC, kOnlyC));
}

TEST(SyncGate, RefusesANegativeBound) { EXPECT_THROW(SyncGate(-1), std::invalid_argument); }

TEST(SyncPace, NoCeilingNeverWaits) {
  SyncPace p(0.0, 100.0, 5.0);
  EXPECT_EQ(p.delay_s(1e6, 5.0), 0.0);
}

TEST(SyncPace, SimulatedTimeRunsAtMostTheScaleTimesWallTime) {
  SyncPace p(45.0, 1000.0, 10.0);
  EXPECT_NEAR(p.delay_s(1000.0 + 4.5, 10.0), 0.1, 1e-12);   // 4.5 s simulated is due 0.1 s of wall later
  EXPECT_NEAR(p.delay_s(1000.0 + 4.5, 10.05), 0.05, 1e-12);
  EXPECT_EQ(p.delay_s(1000.0 + 4.5, 10.2), 0.0);             // behind the pace (within the restart margin)
}

TEST(SyncPace, AfterAStallThePaceRestartsInsteadOfCatchingUp) {
  SyncPace p(10.0, 0.0, 0.0, 0.25);
  EXPECT_EQ(p.delay_s(1.0, 5.0), 0.0);                // 4.9 s behind: a stall; the pace restarts at (1 s, 5 s)
  EXPECT_NEAR(p.delay_s(2.0, 5.0), 0.1, 1e-12) << "the next second of simulated time takes 0.1 s of wall again";
}
