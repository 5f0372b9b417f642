# can/: MM3E frame codec, transports, driver and simulated-device cores, their nodes and tests.
piezo_unit_test(test_can_codec test/unit/test_can_codec.cpp)
piezo_unit_test(test_can_limiter test/unit/test_can_limiter.cpp)
piezo_unit_test(test_can_lockstep test/unit/test_can_lockstep.cpp)
piezo_unit_test(test_can_driver test/unit/test_can_driver.cpp)
# 10^5 random steps of the command path (fixed seed); long mode: PIEZO_PROPERTY_STEPS=10000000
piezo_unit_test(test_can_command_path test/unit/test_can_command_path.cpp)
piezo_node(mm3e_driver src/nodes/mm3e_driver_node.cpp)
piezo_node(mm3e_sim src/nodes/mm3e_sim_node.cpp)
# One checker executable; each .test file is one safety behaviour and selects its case with --gtest_filter.
piezo_rostest(test/rostest/driver_topics.test test/rostest/driver_rostest.cpp DEPENDS mm3e_driver mm3e_sim)
if(CATKIN_ENABLE_TESTING)
  foreach(behaviour command clamp slew nan timeout bus_fault commanders params restart stuck refused)
    piezo_add_rostest(test/rostest/driver_${behaviour}.test DEPENDENCIES driver_topics mm3e_driver mm3e_sim)
  endforeach()
endif()

# libFuzzer target for the codec (clang from Debian, -fsanitize=fuzzer). CTest runs the seeded corpus plus a
# short deterministic mutation run; new inputs go to a scratch directory in the build tree, never to fuzz/.
# Longer runs: devel/lib/piezo_compensation/fuzz_can_codec -max_total_time=600 <scratch> fuzz/corpus/can_codec
find_program(PIEZO_CLANGXX NAMES clang++-14 clang++)
set(PIEZO_FUZZ_CAN ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/fuzz_can_codec)
if(PIEZO_CLANGXX)
  set(fuzz_sources fuzz/fuzz_can_codec.cpp src/core/can/codec.cpp src/core/can/protocol.cpp)
  add_custom_command(OUTPUT ${PIEZO_FUZZ_CAN}
    COMMAND ${PIEZO_CLANGXX} -std=c++17 -O1 -g -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined
            -Wall -Wextra -I${CMAKE_CURRENT_SOURCE_DIR}/include ${fuzz_sources} -lyaml-cpp -o ${PIEZO_FUZZ_CAN}
    DEPENDS ${fuzz_sources} include/piezo_compensation/can/codec.h include/piezo_compensation/can/protocol.h
    WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR}
    COMMENT "Building libFuzzer target fuzz_can_codec with ${PIEZO_CLANGXX}")
  add_custom_target(fuzz_can_codec DEPENDS ${PIEZO_FUZZ_CAN})
  if(TARGET tests)
    add_dependencies(tests fuzz_can_codec)
  endif()
  if(CATKIN_ENABLE_TESTING)
    add_test(NAME fuzz_can_codec_corpus
      COMMAND sh -c "rm -rf fuzz_can_scratch && mkdir -p fuzz_can_scratch && exec '${PIEZO_FUZZ_CAN}' -seed=1 -runs=30000 -max_len=64 fuzz_can_scratch '${CMAKE_CURRENT_SOURCE_DIR}/fuzz/corpus/can_codec'"
      WORKING_DIRECTORY ${CMAKE_BINARY_DIR})
    piezo_test_budget(fuzz_can_codec_corpus)
  endif()
elseif(CATKIN_ENABLE_TESTING)
  add_test(NAME fuzz_can_codec_corpus COMMAND sh -c "echo 'SKIPPED: no clang++-14 (apt-get install clang-14 libclang-rt-14-dev)'; exit 77")
  set_tests_properties(fuzz_can_codec_corpus PROPERTIES SKIP_RETURN_CODE 77)
  piezo_test_budget(fuzz_can_codec_corpus)
endif()

# The real SocketCAN path, inside a throwaway VM with vcan0 (test/vcan/run_vcan_test.sh). The gtest binary is
# not a test of its own: on a kernel without AF_CAN it could only fail. SKIP (77) when the VM cannot start.
if(CATKIN_ENABLE_TESTING)
  catkin_add_executable_with_gtest(test_can_vcan test/vcan/test_can_vcan.cpp)
  target_link_libraries(test_can_vcan piezo_core gtest_main)
  if(TARGET tests)
    add_dependencies(tests test_can_vcan)
  endif()
  add_test(NAME vcan_vm COMMAND ${CMAKE_CURRENT_SOURCE_DIR}/test/vcan/run_vcan_test.sh
           $<TARGET_FILE:test_can_vcan> ${CMAKE_BINARY_DIR}/vcan_vm_work)
  set_tests_properties(vcan_vm PROPERTIES SKIP_RETURN_CODE 77)
  piezo_test_budget(vcan_vm SLOW TIMEOUT 300)  # boots a VM
endif()

# Speed: codec throughput (Google Benchmark) and the command-latency histogram tool; `scripts/piezo bench can`.
piezo_benchmark(bench_can_codec bench/bench_can_codec.cpp)
add_executable(can_command_latency bench/can_command_latency.cpp)
target_link_libraries(can_command_latency piezo_core)
set_target_properties(can_command_latency PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/bench)
if(CATKIN_ENABLE_TESTING)
  add_test(NAME can_command_latency_smoke COMMAND can_command_latency --seconds 0.2)
  piezo_test_budget(can_command_latency_smoke)
endif()
add_executable(can_ros_command_latency bench/can_ros_command_latency.cpp)
target_link_libraries(can_ros_command_latency piezo_ros piezo_core ${catkin_LIBRARIES})
add_dependencies(can_ros_command_latency ${PROJECT_NAME}_generate_messages_cpp mm3e_driver)
set_target_properties(can_ros_command_latency PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/bench)
# Soak: three simulated manipulators through driver + predictor processes at 1 kHz per axis for hours;
# `scripts/piezo bench --soak MINUTES` (docs/driver.md has the figures). Not a ctest: it runs for minutes.
add_executable(can_soak bench/can_soak.cpp)
target_link_libraries(can_soak piezo_ros piezo_core ${catkin_LIBRARIES})
target_compile_definitions(can_soak PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
add_dependencies(can_soak ${PROJECT_NAME}_generate_messages_cpp mm3e_driver piezo_predictor)
set_target_properties(can_soak PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/bench)
