// libFuzzer target for the CAN codec: decode() must accept any bytes without crashing, and anything it decodes
// must re-encode to a frame that decodes to the same message (round trip). Input: 1 byte choosing the protocol
// variant, 16 bytes of struct can_frame, then optional text for the candump parser.
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>

#include "piezo_compensation/can/codec.h"

using namespace piezo::can;

namespace {

const Codec& codec_for(std::uint8_t variant) {
  static const Codec codecs[4] = {
      Codec(ProtocolConfig{}),
      [] {
        ProtocolConfig c;
        c.byte_order = ByteOrder::kBig;
        return Codec(c);
      }(),
      [] {
        ProtocolConfig c;
        c.extended_ids = true;
        c.base_node_id = 0x1234;
        c.node_id_stride = 16;
        return Codec(c);
      }(),
      [] {
        ProtocolConfig c;
        c.voltage_lsb_v = 0.01;
        c.position_lsb_m = 1e-12;
        return Codec(c);
      }(),
  };
  return codecs[variant % 4];
}

void check(bool ok, const char* what) {
  if (!ok) {
    std::fprintf(stderr, "invariant violated: %s\n", what);
    std::abort();
  }
}

bool same_frame(const can_frame& a, const can_frame& b) {
  const int len = a.can_dlc > 8 ? 8 : a.can_dlc;
  return a.can_id == b.can_id && a.can_dlc == b.can_dlc && std::memcmp(a.data, b.data, len) == 0;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size < 1 + sizeof(can_frame)) return 0;
  const Codec& codec = codec_for(data[0]);
  can_frame f;
  std::memcpy(&f, data + 1, sizeof f);
  const DecodeResult r = codec.decode(f);
  check(r.ok() == r.message.empty(), "error message iff error");
  if (r.ok()) {
    can_frame again;
    bool encoded = true;
    if (const auto* m = std::get_if<CommandFrame>(&r.message_value)) {
      check(std::isfinite(m->voltage_v), "decoded voltage finite");
      again = codec.encode(*m);
    } else if (const auto* m = std::get_if<VoltageReport>(&r.message_value)) {
      again = codec.encode(*m);
    } else if (const auto* m = std::get_if<EncoderReport>(&r.message_value)) {
      check(std::isfinite(m->position_m), "decoded position finite");
      again = codec.encode(*m);
    } else if (const auto* m = std::get_if<Heartbeat>(&r.message_value)) {
      again = codec.encode(*m);
    } else if (const auto* m = std::get_if<SyncFrame>(&r.message_value)) {
      again = codec.encode(*m);
    } else {
      encoded = false;  // error frames: only the class bits and data are kept
      check(!std::get<BusError>(r.message_value).description.empty(), "error frame described");
    }
    if (encoded) {
      // Padding bytes beyond the DLC are not part of the frame; everything else must survive.
      can_frame canonical = f;
      if (!(canonical.can_id & CAN_EFF_FLAG)) canonical.can_id &= CAN_SFF_MASK;
      check(same_frame(canonical, again), "decode → encode reproduces the frame");
      check(codec.decode(again).ok(), "re-encoded frame decodes");
    }
  }
  SequenceTracker t;
  for (std::size_t i = 1; i + 3 <= size; i += 3) t.update(data[i] | data[i + 1] << 8 | data[i + 2] << 16);
  if (size > 1 + sizeof(can_frame)) {
    const std::string text(reinterpret_cast<const char*>(data) + 1 + sizeof(can_frame), size - 1 - sizeof(can_frame));
    try {
      const can_frame parsed = from_candump(text);
      check(same_frame(from_candump(to_candump(parsed)), parsed), "candump text round trip");
    } catch (const std::invalid_argument&) {
    }
  }
  return 0;
}
