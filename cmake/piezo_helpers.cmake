# Helpers the part files use, so each part declares its targets in one line each.

# piezo_node(<name> <sources...>): a thin ROS node executable linked against the wrappers.
function(piezo_node name)
  add_executable(${name} ${ARGN})
  target_link_libraries(${name} piezo_ros piezo_core ${catkin_LIBRARIES})
  add_dependencies(${name} ${PROJECT_NAME}_generate_messages_cpp)
  install(TARGETS ${name} RUNTIME DESTINATION ${CATKIN_PACKAGE_BIN_DESTINATION})
endfunction()

# piezo_unit_test(<name> <sources...>): a plain GoogleTest executable on the ROS-free core.
function(piezo_unit_test name)
  if(CATKIN_ENABLE_TESTING)
    catkin_add_gtest(${name} ${ARGN} WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR})
    target_link_libraries(${name} piezo_core gtest_main)
    target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
  endif()
endfunction()

# piezo_ros_unit_test(<name> <sources...>): GoogleTest that needs the ROS-side library but no roscore.
function(piezo_ros_unit_test name)
  if(CATKIN_ENABLE_TESTING)
    catkin_add_gtest(${name} ${ARGN} WORKING_DIRECTORY ${CMAKE_CURRENT_SOURCE_DIR})
    target_link_libraries(${name} piezo_ros piezo_core ${catkin_LIBRARIES} gtest_main)
    target_compile_definitions(${name} PRIVATE PIEZO_SOURCE_DIR="${CMAKE_CURRENT_SOURCE_DIR}")
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
    add_dependencies(${name} ${PROJECT_NAME}_generate_messages_cpp piezo ${ARG_DEPENDS})
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
  endif()
endfunction()
