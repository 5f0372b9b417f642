# sim/ and protocols/: the simulated MM3E, the data-collection protocols, bag I/O and `piezo simulate`.
piezo_unit_test(test_sim_physics test/unit/test_sim_physics.cpp)
piezo_unit_test(test_sim_effects test/unit/test_sim_effects.cpp)
piezo_unit_test(test_sim_stages test/unit/test_sim_stages.cpp)
piezo_unit_test(test_io_controller_log test/unit/test_io_controller_log.cpp)
piezo_unit_test(test_recordings test/unit/test_recordings.cpp)
piezo_unit_test(test_protocols_generators test/unit/test_protocols_generators.cpp)
piezo_ros_unit_test(test_bag_io test/unit/test_bag_io.cpp)
piezo_benchmark(bench_simulator bench/bench_simulator.cpp)
# `piezo simulate` end to end: every protocol name accepted, a bag written and read back by `piezo info`.
if(CATKIN_ENABLE_TESTING)
  add_test(NAME cli_simulate_smoke COMMAND sh -c
    "set -e; d=$(mktemp -d); \
     $<TARGET_FILE:piezo> simulate --protocol sawtooth --seed 2 --effect thermal_drift --out $d/s.bag; \
     $<TARGET_FILE:piezo> info $d/s.bag | grep -q 'aux: temperature_c'; \
     $<TARGET_FILE:piezo> simulate --protocol noise --axes c --duration 30 --out $d/n.csv; \
     head -1 $d/n.csv | grep -qx '# origin: simulated'; test $(wc -l < $d/n.csv) -eq 332; \
     ! $<TARGET_FILE:piezo> simulate --protocol nosuch --out $d/x.csv 2>/dev/null; \
     $<TARGET_FILE:piezo> simulate --stage ${CMAKE_CURRENT_SOURCE_DIR}/config/stages/lowvolt_preisach_creep.yaml --duration 2 --out $d/st.csv; \
     test $(wc -l < $d/st.csv) -eq 402; \
     ! $<TARGET_FILE:piezo> simulate --stage ${CMAKE_CURRENT_SOURCE_DIR}/config/stages/mm3e_pi.yaml --protocol noise --out $d/x.csv 2>/dev/null; \
     rm -rf $d")
  piezo_test_budget(cli_simulate_smoke)
endif()
piezo_unit_test(test_sim_thermal_switch test/unit/test_sim_thermal_switch.cpp)
