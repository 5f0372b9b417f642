// Codec throughput: the driver decodes every frame on the bus and encodes every command.
#include <benchmark/benchmark.h>

#include "piezo_compensation/can/codec.h"

using namespace piezo::can;

static void BM_CanEncodeCommand(benchmark::State& state) {
  const Codec codec{ProtocolConfig{}};
  double v = 0.0;
  for (auto _ : state) {
    can_frame f = codec.encode(CommandFrame{1, v, 7});
    benchmark::DoNotOptimize(f);
    v += 1e-3;
    if (v > 80) v = -80;
  }
}
BENCHMARK(BM_CanEncodeCommand);

static void BM_CanDecodeEncoder(benchmark::State& state) {
  const Codec codec{ProtocolConfig{}};
  const can_frame f = codec.encode(EncoderReport{2, 1.5e-6, 12345, true});
  for (auto _ : state) {
    DecodeResult r = codec.decode(f);
    benchmark::DoNotOptimize(r);
  }
}
BENCHMARK(BM_CanDecodeEncoder);

static void BM_CanDecodeUnknownId(benchmark::State& state) {
  const Codec codec{ProtocolConfig{}};
  const can_frame f = from_candump("123#DEADBEEF");
  for (auto _ : state) {
    DecodeResult r = codec.decode(f);
    benchmark::DoNotOptimize(r);
  }
}
BENCHMARK(BM_CanDecodeUnknownId);

BENCHMARK_MAIN();
