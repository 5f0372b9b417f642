// Codec, protocol config and sequence tracking: round trips and every malformed-frame kind.
#include <gtest/gtest.h>
#include <linux/can/error.h>
#include <yaml-cpp/yaml.h>

#include <cmath>
#include <cstring>
#include <limits>

#include "piezo_compensation/can/codec.h"
#include "piezo_compensation/can/transport.h"

using namespace piezo::can;

namespace {

template <typename T>
T decode_as(const Codec& codec, const can_frame& f) {
  const DecodeResult r = codec.decode(f);
  EXPECT_TRUE(r.ok()) << r.message;
  const T* m = std::get_if<T>(&r.message_value);
  EXPECT_NE(m, nullptr);
  return m ? *m : T{};
}

ProtocolConfig big_endian_extended() {
  ProtocolConfig c;
  c.byte_order = ByteOrder::kBig;
  c.extended_ids = true;
  c.base_node_id = 0x12345;
  return c;
}

}  // namespace

TEST(CanCodec, IdentifiersFollowBaseNodeId) {
  ProtocolConfig c;
  c.base_node_id = 0x20;
  c.node_id_stride = 4;
  Codec codec(c);
  EXPECT_EQ(codec.command_id(0), 0x220u);
  EXPECT_EQ(codec.command_id(2), 0x228u);
  EXPECT_EQ(codec.voltage_id(1), 0x1A4u);
  EXPECT_EQ(codec.encoder_id(2), 0x2A8u);
  EXPECT_EQ(codec.heartbeat_id(), 0x720u);
  EXPECT_EQ(codec.sync_id(), 0x0A0u);  // CANopen SYNC function code + base node: two manipulators stay apart
}

TEST(CanCodec, RoundTripEveryKindBothByteOrders) {
  for (const ProtocolConfig& c : {ProtocolConfig{}, big_endian_extended()}) {
    Codec codec(c);
    for (int axis = 0; axis < kAxisCount; ++axis) {
      const auto cmd = decode_as<CommandFrame>(codec, codec.encode(CommandFrame{axis, -79.12345, 0xDEADBEEF}));
      EXPECT_EQ(cmd.axis, axis);
      EXPECT_NEAR(cmd.voltage_v, -79.12345, 0.51 * c.voltage_lsb_v);
      EXPECT_EQ(cmd.counter, 0xDEADBEEFu);

      const auto v = decode_as<VoltageReport>(codec, codec.encode(VoltageReport{axis, 42.5, 0xABCDEF, true}));
      EXPECT_EQ(v.axis, axis);
      EXPECT_NEAR(v.voltage_v, 42.5, 0.51 * c.voltage_lsb_v);
      EXPECT_EQ(v.sequence, 0xABCDEFu);
      EXPECT_TRUE(v.fault);

      const auto e = decode_as<EncoderReport>(codec, codec.encode(EncoderReport{axis, -1.234567e-6, 7, false}));
      EXPECT_EQ(e.axis, axis);
      EXPECT_NEAR(e.position_m, -1.234567e-6, 0.51 * c.position_lsb_m);
      EXPECT_EQ(e.sequence, 7u);
      EXPECT_FALSE(e.valid);
    }
    const auto h = decode_as<Heartbeat>(codec, codec.encode(Heartbeat{DeviceState::kHalted, 0x85, 0xBEEF}));
    EXPECT_EQ(h.state, DeviceState::kHalted);
    EXPECT_EQ(h.fault_flags, 0x85);
    EXPECT_EQ(h.counter, 0xBEEF);
    const can_frame sync = codec.encode(SyncFrame{200});
    EXPECT_EQ(sync.can_dlc, 1);
    EXPECT_EQ(decode_as<SyncFrame>(codec, sync).counter, 200);
  }
}

TEST(CanCodec, SyncFrameIsTheDevicesOnly) {
  Codec codec{ProtocolConfig{}};
  can_frame sync = codec.encode(SyncFrame{1});
  EXPECT_EQ(sync.can_id, 0x090u);
  auto passes = [&sync](const std::vector<can_filter>& filters) {
    for (const auto& f : filters)
      if ((sync.can_id & f.can_mask) == (f.can_id & f.can_mask)) return true;
    return false;
  };
  EXPECT_TRUE(passes(codec.device_filters()));
  EXPECT_FALSE(passes(codec.driver_filters()));
  sync.can_dlc = 0;  // CANopen allows an empty SYNC; this protocol always carries the counter
  EXPECT_EQ(codec.decode(sync).error, DecodeError::kBadLength);
}

TEST(CanCodec, ByteOrderIsOnTheWire) {
  Codec little{ProtocolConfig{}};
  ProtocolConfig bc;
  bc.byte_order = ByteOrder::kBig;
  Codec big{bc};
  // 1 V = 10000 counts = 0x2710
  const can_frame fl = little.encode(CommandFrame{0, 1.0, 0});
  const can_frame fb = big.encode(CommandFrame{0, 1.0, 0});
  EXPECT_EQ(to_candump(fl), "210#1027000000000000");
  EXPECT_EQ(to_candump(fb), "210#0000271000000000");
  // The same bytes mean something else in the other order: the config, not the code, decides.
  EXPECT_NE(decode_as<CommandFrame>(big, fl).voltage_v, 1.0);
}

TEST(CanCodec, SequenceIs24BitOnTheWire) {
  Codec codec{ProtocolConfig{}};
  const auto v = decode_as<VoltageReport>(codec, codec.encode(VoltageReport{0, 0.0, 0x1000005, false}));
  EXPECT_EQ(v.sequence, 5u);
}

TEST(CanCodec, EncodeRefusesNonFiniteAndOutOfRange) {
  Codec codec{ProtocolConfig{}};
  EXPECT_THROW(codec.encode(CommandFrame{0, std::nan(""), 0}), std::invalid_argument);
  EXPECT_THROW(codec.encode(CommandFrame{0, std::numeric_limits<double>::infinity(), 0}), std::invalid_argument);
  EXPECT_THROW(codec.encode(CommandFrame{0, 1e9, 0}), std::invalid_argument);  // does not fit int32 counts
  EXPECT_THROW(codec.encode(CommandFrame{3, 1.0, 0}), std::invalid_argument);
  EXPECT_THROW(codec.encode(EncoderReport{-1, 0.0, 0, true}), std::invalid_argument);
  EXPECT_THROW(codec.encode(EncoderReport{0, 10.0, 0, true}), std::invalid_argument);  // 10 m in nm counts
}

TEST(CanCodec, MalformedUnknownId) {
  Codec codec{ProtocolConfig{}};
  const auto r = codec.decode(from_candump("123#0102030405060708"));
  EXPECT_EQ(r.error, DecodeError::kUnknownId);
  EXPECT_NE(r.message.find("0x123"), std::string::npos) << r.message;
  // Axis d does not exist: base + 3 is not ours.
  EXPECT_EQ(codec.decode(from_candump("193#0000000000000000")).error, DecodeError::kUnknownId);
}

TEST(CanCodec, MalformedRemoteFrame) {
  Codec codec{ProtocolConfig{}};
  can_frame f = codec.encode(VoltageReport{1, 1.0, 1, false});
  f.can_id |= CAN_RTR_FLAG;
  EXPECT_EQ(codec.decode(f).error, DecodeError::kRemoteFrame);
}

TEST(CanCodec, MalformedWrongIdFormat) {
  Codec codec{ProtocolConfig{}};
  can_frame f = codec.encode(EncoderReport{0, 0.0, 1, true});
  f.can_id |= CAN_EFF_FLAG;
  EXPECT_EQ(codec.decode(f).error, DecodeError::kWrongIdFormat);
  Codec ext{big_endian_extended()};
  can_frame g = ext.encode(EncoderReport{0, 0.0, 1, true});
  g.can_id &= ~CAN_EFF_FLAG;
  g.can_id &= CAN_SFF_MASK;  // an 11-bit id cannot carry it: becomes unknown or wrong format, never decoded
  EXPECT_FALSE(ext.decode(g).ok());
}

TEST(CanCodec, MalformedBadLength) {
  Codec codec{ProtocolConfig{}};
  for (std::uint8_t dlc : {0, 3, 7, 9, 15, 255}) {
    can_frame f = codec.encode(VoltageReport{2, 1.0, 1, false});
    f.can_dlc = dlc;
    const auto r = codec.decode(f);
    EXPECT_EQ(r.error, DecodeError::kBadLength) << int(dlc);
    EXPECT_NE(r.message.find("DLC"), std::string::npos);
  }
  can_frame h = codec.encode(Heartbeat{});
  h.can_dlc = 8;
  EXPECT_EQ(codec.decode(h).error, DecodeError::kBadLength);
  can_frame err = Codec::encode(BusError{CAN_ERR_BUSOFF, true, false, false, {}, ""});
  err.can_dlc = 2;
  EXPECT_EQ(codec.decode(err).error, DecodeError::kBadLength);
}

TEST(CanCodec, MalformedBadField) {
  Codec codec{ProtocolConfig{}};
  can_frame f = codec.encode(EncoderReport{0, 0.0, 1, true});
  f.data[7] = 0x80;  // reserved flag bit
  EXPECT_EQ(codec.decode(f).error, DecodeError::kBadField);
  can_frame h = codec.encode(Heartbeat{});
  h.data[0] = 9;  // no such device state
  const auto r = codec.decode(h);
  EXPECT_EQ(r.error, DecodeError::kBadField);
  EXPECT_NE(r.message.find("state 9"), std::string::npos);
}

TEST(CanCodec, ErrorFramesAreDescribed) {
  Codec codec{ProtocolConfig{}};
  BusError in;
  in.error_class = CAN_ERR_BUSOFF | CAN_ERR_CRTL;
  in.data[1] = CAN_ERR_CRTL_TX_PASSIVE;
  const auto e = decode_as<BusError>(codec, Codec::encode(in));
  EXPECT_TRUE(e.bus_off);
  EXPECT_TRUE(e.error_passive);
  EXPECT_NE(e.description.find("bus-off"), std::string::npos);
  EXPECT_NE(e.description.find("tx error passive"), std::string::npos);
  const auto r = decode_as<BusError>(codec, Codec::encode(BusError{CAN_ERR_RESTARTED, false, false, true, {}, ""}));
  EXPECT_TRUE(r.restarted);
  EXPECT_FALSE(r.bus_off);
}

TEST(CanCodec, FiltersPassOnlyOwnFrames) {
  Codec codec{ProtocolConfig{}};
  const auto df = codec.driver_filters();
  EXPECT_TRUE(passes_filters(codec.encode(EncoderReport{1, 0.0, 1, true}), df));
  EXPECT_TRUE(passes_filters(codec.encode(Heartbeat{}), df));
  EXPECT_FALSE(passes_filters(codec.encode(CommandFrame{1, 0.0, 1}), df));
  EXPECT_FALSE(passes_filters(from_candump("123#00"), df));
  can_frame rtr = codec.encode(EncoderReport{1, 0.0, 1, true});
  rtr.can_id |= CAN_RTR_FLAG;
  EXPECT_FALSE(passes_filters(rtr, df));
  EXPECT_TRUE(passes_filters(Codec::encode(BusError{CAN_ERR_BUSOFF, true, false, false, {}, ""}), df));  // error frames always pass
  const auto dev = codec.device_filters();
  EXPECT_TRUE(passes_filters(codec.encode(CommandFrame{2, 0.0, 1}), dev));
  EXPECT_FALSE(passes_filters(codec.encode(VoltageReport{2, 0.0, 1, false}), dev));
}

TEST(CanCodec, CandumpTextRoundTrip) {
  for (const char* text : {"123#DEADBEEF", "12345678#0011", "7FF#", "210#R"}) EXPECT_EQ(to_candump(from_candump(text)), text);
  EXPECT_EQ(to_candump(from_candump("5A1#11.22")), "5A1#1122");
  for (const char* bad : {"", "12#00", "800#00", "123#0", "123#GG", "123#001122334455667788", "XYZ#00"})
    EXPECT_THROW(from_candump(bad), std::invalid_argument) << bad;
}

TEST(CanSequence, CountsDropsReorderAndWrap) {
  SequenceTracker t;
  EXPECT_EQ(t.update(10).dropped, 0u);
  EXPECT_EQ(t.update(11).dropped, 0u);
  auto u = t.update(14);
  EXPECT_EQ(u.dropped, 2u);
  EXPECT_EQ(u.sequence, 14u);
  EXPECT_TRUE(t.update(14).out_of_order);  // duplicate
  EXPECT_FALSE(t.update(14).restarted);
  u = t.update(13);  // any step back: one controller never reorders its frames, so it restarted
  EXPECT_TRUE(u.restarted);
  EXPECT_EQ(u.sequence, 13u);
  EXPECT_EQ(t.update(14).dropped, 0u);  // re-anchored there
  SequenceTracker w;
  w.update(kSequenceModulo - 1);
  u = w.update(0);  // 24-bit wrap: continues past 2^24 in 32 bit
  EXPECT_EQ(u.dropped, 0u);
  EXPECT_FALSE(u.out_of_order);
  EXPECT_EQ(u.sequence, kSequenceModulo);
  SequenceTracker r;
  r.update(500000);
  u = r.update(0);  // far back: device restarted
  EXPECT_TRUE(u.restarted);
  EXPECT_EQ(r.update(1).dropped, 0u);
  SequenceTracker s;  // a restart within a few samples of power-up is a short step back: still a restart
  s.update(7);
  EXPECT_TRUE(s.update(0).restarted);
}

TEST(CanProtocol, ValidationNamesTheField) {
  ProtocolConfig c;
  c.voltage_lsb_v = 0;
  try {
    validate(c);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("voltage_lsb_v"), std::string::npos);
  }
  c = ProtocolConfig{};
  c.encoder_function_id = c.voltage_function_id;  // two frames on one identifier
  EXPECT_THROW(validate(c), std::invalid_argument);
  c = ProtocolConfig{};
  c.sync_function_id = c.voltage_function_id;  // SYNC on axis a's voltage report identifier
  try {
    validate(c);
    FAIL();
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("sync_function_id"), std::string::npos) << e.what();
  }
  c = ProtocolConfig{};
  c.base_node_id = 0x7F0;  // heartbeat 0x700 + 0x7F0 exceeds 11 bit
  EXPECT_THROW(validate(c), std::invalid_argument);
  c.extended_ids = true;
  EXPECT_NO_THROW(validate(c));
  c = ProtocolConfig{};
  c.encoder_rate_hz = std::nan("");
  EXPECT_THROW(validate(c), std::invalid_argument);
}

TEST(CanProtocol, YamlFieldsAndErrors) {
  const auto c = protocol_from_yaml(YAML::Load("{base_node_id: 0x30, byte_order: big, voltage_lsb_v: 0.001}"));
  EXPECT_EQ(c.base_node_id, 0x30u);
  EXPECT_EQ(c.byte_order, ByteOrder::kBig);
  EXPECT_DOUBLE_EQ(c.voltage_lsb_v, 0.001);
  EXPECT_DOUBLE_EQ(c.encoder_rate_hz, 11.0);  // default kept
  auto message_of = [](const char* yaml) {
    try {
      protocol_from_yaml(YAML::Load(yaml));
    } catch (const std::invalid_argument& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(message_of("{byte_order: middle}").find("byte_order"), std::string::npos);
  EXPECT_NE(message_of("{base_node_id: -1}").find("base_node_id"), std::string::npos);
  EXPECT_NE(message_of("{position_lsb_m: abc}").find("position_lsb_m"), std::string::npos);
  EXPECT_NE(message_of("[1, 2]").find("protocol"), std::string::npos);
}

TEST(CanProtocol, ShippedConfigLoads) {
  const auto c = load_protocol_config(std::string(PIEZO_SOURCE_DIR) + "/config/mm3e.yaml");
  EXPECT_DOUBLE_EQ(c.encoder_rate_hz, 11.0);
  EXPECT_THROW(load_protocol_config("/nonexistent/mm3e.yaml"), std::invalid_argument);
}
