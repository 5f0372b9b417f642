# Helpers the part files use, so each part declares its targets in one line each.

# piezo_node(<name> <sources...>): a thin ROS node executable linked against the wrappers.
function(piezo_node name)
  add_executable(${name} ${ARGN})
  target_link_libraries(${name} piezo_ros piezo_core ${catkin_LIBRARIES})
  add_dependencies(${name} ${PROJECT_NAME}_generate_messages_cpp)
  install(TARGETS ${name} RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})
endfunction()

# ---- test budgets -------------------------------------------------------------------------------------------
# Every CTest test has LABELS fast or slow and a TIMEOUT (the helpers below set them; a test added with a plain
# add_test calls piezo_test_budget, and CMakeLists.txt refuses a test without both). `ctest -L fast` is the quick
# loop: each fast test takes seconds; slow ones up to the suite's rule of 60 s each on the 2-core CI machine. The
# TIMEOUT only catches a hang, with room for a host shared with builds (load 10 on 2 cores stretched the 67-s
# test_models_preisach past 180 s): fast 120 s, slow 600 s, a rostest its .test file's time-limit plus 30 s for the
# master and the nodes to start and stop.
set(PIEZO_FAST_TIMEOUT_S 120)
set(PIEZO_SLOW_TIMEOUT_S 600)
set(PIEZO_TIMEOUT_SCALE 1 CACHE STRING "Every test TIMEOUT times this (scripts/test-sanitize: 10, ASan is 5-10x slower)")

# piezo_test_budget(<ctest test name> [SLOW] [TIMEOUT seconds]): label fast (default) or slow, and a timeout.
function(piezo_test_budget test)
  cmake_parse_arguments(ARG "SLOW" "TIMEOUT" "" ${ARGN})
  if(ARG_SLOW)
    set(label slow)
    set(timeout ${PIEZO_SLOW_TIMEOUT_S})
  else()
    set(label fast)
    set(timeout ${PIEZO_FAST_TIMEOUT_S})
  endif()
  if(ARG_TIMEOUT)
    set(timeout ${ARG_TIMEOUT})
  endif()
  math(EXPR timeout "${timeout} * ${PIEZO_TIMEOUT_SCALE}")
  # COST: a fresh build tree has no CTest timing record, so `ctest -j2` would start tests in the order they are
  # declared and end on a long slow one alone; the slow ones start first instead (later runs use the record).
  if(label STREQUAL "slow")
    set(cost 100)
  else()
    set(cost 1)
  endif()
  # RESOURCE_GROUPS (used when ctest gets scripts/test's --resource-spec-file): a rostest mostly waits on its nodes
  # and simulated time (hold_trim: 25 s of CPU in 35 s, driver_clamp 1.7 s in 7 s), so it takes a `ros` slot and
  # runs beside the tests that compute, each of which takes a `cpu` slot (one per core).
  if(test MATCHES "_rostest_")
    set(resources ros:1)
  else()
    set(resources cpu:1)
  endif()
  set_tests_properties(${test} PROPERTIES LABELS ${label} TIMEOUT ${timeout} COST ${cost} RESOURCE_GROUPS ${resources})
  # A slow computing test has one core (its cpu slot): the trainer's OpenMP shards run on one thread (the same
  # result for 1 or 2 threads, training/trainer.cpp). Two threads on a core another test is using wait at every
  # barrier for the one descheduled, and spin while they wait.
  if(label STREQUAL "slow" AND NOT test MATCHES "_rostest_")
    set_property(TEST ${test} APPEND PROPERTY ENVIRONMENT OMP_THREAD_LIMIT=1)
  endif()
endfunction()

# The CTest name of a test declared by the helpers: a gtest target, a rostest launch file's base name, or a
# test added by name.
function(piezo_ctest_name out name)
  if(TEST _ctest_${PROJECT_NAME}_gtest_${name})
    set(${out} _ctest_${PROJECT_NAME}_gtest_${name} PARENT_SCOPE)
  elseif(TEST _ctest_${PROJECT_NAME}_rostest_test_rostest_${name}.test)
    set(${out} _ctest_${PROJECT_NAME}_rostest_test_rostest_${name}.test PARENT_SCOPE)
  elseif(TEST ${name})
    set(${out} ${name} PARENT_SCOPE)
  else()
    message(FATAL_ERROR "piezo_ctest_name: no test '${name}'")
  endif()
endfunction()

# piezo_slow_tests(<names...>): these tests are slow (gtest target names, rostest base names or test names);
# each part lists its own once, after declaring them.
function(piezo_slow_tests)
  if(CATKIN_ENABLE_TESTING)
    foreach(name ${ARGN})
      piezo_ctest_name(test ${name})
      get_test_property(${test} TIMEOUT timeout)
      if(test MATCHES "_rostest_")
        piezo_test_budget(${test} SLOW TIMEOUT ${timeout})  # keeps the launch file's time-limit
      else()
        piezo_test_budget(${test} SLOW)
      endif()
    endforeach()
  endif()
endfunction()

# Fails the configuration when a test has no LABELS or no TIMEOUT (called once all parts are in).
function(piezo_check_test_budgets)
  get_property(tests DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR} PROPERTY TESTS)
  foreach(test ${tests})
    get_test_property(${test} LABELS labels)
    get_test_property(${test} TIMEOUT timeout)
    if(NOT labels OR NOT timeout)
      message(FATAL_ERROR "test ${test} has no LABELS or TIMEOUT: declare it with the helpers of "
                          "cmake/piezo_helpers.cmake or call piezo_test_budget(${test})")
    endif()
  endforeach()
endfunction()

# A rostest's budget: the time-limit of its launch file's <test> plus the start and stop of master and nodes.
# Rostests are slow (a master, nodes, real or simulated time); `ctest -L fast` leaves them out.
function(piezo_rostest_budget launch_file)
  get_filename_component(name ${launch_file} NAME)
  file(READ ${CMAKE_CURRENT_SOURCE_DIR}/${launch_file} text)
  set(limit 60)  # rostest's default time-limit
  if(text MATCHES "time-limit=\"([0-9.]+)\"")
    set(limit ${CMAKE_MATCH_1})
  endif()
  math(EXPR timeout "${limit} + 30")
  piezo_test_budget(_ctest_${PROJECT_NAME}_rostest_test_rostest_${name} SLOW TIMEOUT ${timeout})
endfunction()

# piezo_add_rostest(<launch file> [DEPENDENCIES targets...]): another launch file for an existing checker.
function(piezo_add_rostest launch_file)
  if(CATKIN_ENABLE_TESTING)
    add_rostest(${launch_file} ${ARGN})
    piezo_rostest_budget(${launch_file})
  endif()
endfunction()

# ---- how test code is compiled ------------------------------------------------------------------------------
# Test code is compiled at -O1: the work a test waits for runs in the -O3 core library, and the GoogleTest macros
# of ~60 test files at -O3 were half of a fresh build's compile time. The plain unit tests share one precompiled
# header (GoogleTest, Eigen, yaml-cpp and the standard library), built once by piezo_test_pch.
set(PIEZO_TEST_OPT -O1)
if(CATKIN_ENABLE_TESTING)
  add_library(piezo_test_pch STATIC EXCLUDE_FROM_ALL ${CMAKE_CURRENT_SOURCE_DIR}/test/unit/pch_anchor.cpp)
  target_link_libraries(piezo_test_pch PUBLIC piezo_core GTest::gtest gtest_main)  # as catkin_add_gtest links
  target_compile_definitions(piezo_test_pch PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
  target_compile_options(piezo_test_pch PRIVATE ${PIEZO_TEST_OPT})
  target_precompile_headers(piezo_test_pch PRIVATE <gtest/gtest.h> <Eigen/Dense> <yaml-cpp/yaml.h> <algorithm>
                            <cmath> <functional> <map> <memory> <string> <vector>)
endif()

# piezo_test_code(<target>): compile a test target's own code as test code (above); PCH: also share the header.
function(piezo_test_code target)
  cmake_parse_arguments(ARG "PCH" "" "" ${ARGN})
  target_compile_options(${target} PRIVATE ${PIEZO_TEST_OPT})
  if(ARG_PCH)
    target_precompile_headers(${target} REUSE_FROM piezo_test_pch)
  endif()
endfunction()

# piezo_unit_test(<name> <sources...>): a plain GoogleTest executable on the ROS-free core.
function(piezo_unit_test name)
  if(CATKIN_ENABLE_TESTING)
    catkin_add_gtest(${name} ${ARGN} WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR})
    target_link_libraries(${name} piezo_core gtest_main)
    target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
    piezo_test_code(${name} PCH)
    piezo_test_budget(_ctest_${PROJECT_NAME}_gtest_${name})
  endif()
endfunction()

# piezo_unit_test_shards(<name> <sources...> SHARDS <suffix> <gtest filter> [<suffix> <gtest filter>...]): one
# test binary, one CTest test <name>_<suffix> per filter, so CTest can run the parts in parallel.
function(piezo_unit_test_shards name)
  if(CATKIN_ENABLE_TESTING)
    cmake_parse_arguments(ARG "" "" "SHARDS" ${ARGN})
    catkin_add_executable_with_gtest(${name} ${ARG_UNPARSED_ARGUMENTS} EXCLUDE_FROM_ALL)
    target_link_libraries(${name} piezo_core gtest_main)
    target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
    piezo_test_code(${name} PCH)
    add_dependencies(tests ${name})
    get_target_property(dir ${name} RUNTIME_OUTPUT_DIRECTORY)
    set(shards ${ARG_SHARDS})
    while(shards)
      list(POP_FRONT shards suffix filter)
      set(xml gtest-${name}_${suffix}.xml)
      catkin_run_tests_target("gtest" ${name}_${suffix} ${xml}
        COMMAND "${dir}/${name} '--gtest_filter=${filter}' --gtest_output=xml:${CATKIN_TEST_RESULTS_DIR}/${PROJECT_NAME}/${xml}"
        DEPENDENCIES ${name} WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR})
      piezo_test_budget(_ctest_${PROJECT_NAME}_gtest_${name}_${suffix})
    endwhile()
  endif()
endfunction()

# piezo_reference_fixture(<setup test> <env var> <file> <tests...>): the setup test (a gtest target or shard name)
# writes a figure to <file> once per ctest run; the tests need it first and find <file> in <env var>.
function(piezo_reference_fixture setup var file)
  if(CATKIN_ENABLE_TESTING)
    piezo_ctest_name(test ${setup})
    set_tests_properties(${test} PROPERTIES FIXTURES_SETUP ${setup})
    set_property(TEST ${test} APPEND PROPERTY ENVIRONMENT ${var}=${file})
    foreach(name ${ARGN})
      piezo_ctest_name(test ${name})
      set_tests_properties(${test} PROPERTIES FIXTURES_REQUIRED ${setup})
      set_property(TEST ${test} APPEND PROPERTY ENVIRONMENT ${var}=${file})
    endforeach()
  endif()
endfunction()

# piezo_ros_unit_test(<name> <sources...>): GoogleTest that needs the ROS-side library but no roscore.
function(piezo_ros_unit_test name)
  if(CATKIN_ENABLE_TESTING)
    catkin_add_gtest(${name} ${ARGN} WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR})
    target_link_libraries(${name} piezo_ros piezo_core ${catkin_LIBRARIES} gtest_main)
    target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
    piezo_test_code(${name})
    piezo_test_budget(_ctest_${PROJECT_NAME}_gtest_${name})
  endif()
endfunction()

# piezo_rostest(<launch file> <gtest sources...> [DEPENDS targets...]): a rostest with a gtest checker.
function(piezo_rostest launch_file)
  if(CATKIN_ENABLE_TESTING)
    cmake_parse_arguments(ARG "" "" "DEPENDS" ${ARGN})
    get_filename_component(name ${launch_file} NAME_WE)
    add_rostest_gtest(${name} ${launch_file} ${ARG_UNPARSED_ARGUMENTS})
    target_link_libraries(${name} piezo_ros piezo_core ${catkin_LIBRARIES})
    target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
    piezo_test_code(${name})
    add_dependencies(${name} ${PROJECT_NAME}_generate_messages_cpp piezo ${ARG_DEPENDS})
    piezo_rostest_budget(${launch_file})
  endif()
endfunction()

# piezo_benchmark(<name> <sources...>): a Google Benchmark target. `scripts/piezo bench` runs them with
# real timings; CTest runs each once with a tiny time budget so they cannot rot (no timing is asserted).
function(piezo_benchmark name)
  if(NOT benchmark_FOUND)
    message(FATAL_ERROR "Google Benchmark (libbenchmark-dev) is required for ${name}")
  endif()
  add_executable(${name} ${ARGN})
  target_link_libraries(${name} piezo_core benchmark::benchmark)
  target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
  set_target_properties(${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/bench)
  if(CATKIN_ENABLE_TESTING)
    add_test(NAME ${name}_smoke COMMAND ${name} --benchmark_min_time=0.001)
    piezo_test_budget(${name}_smoke)
    add_dependencies(tests ${name})  # `make tests` rebuilds what ctest runs (a stale benchmark after a core header change crashes)
  endif()
endfunction()
