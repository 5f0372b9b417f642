# libFuzzer targets for the file readers (fuzz/fuzz_readers.cpp: CSV, model file, protocol YAML; fuzz/fuzz_bag.cpp:
# the bag reader; the CAN codec's target is in can.cmake). The reader code is compiled with clang, coverage + ASan + UBSan, one object per core
# source so make builds them in parallel and only again when a source changes. CTest runs each seed corpus in
# fuzz/corpus/<reader> plus a short deterministic mutation run (new inputs go to a scratch directory in the
# build tree). Longer runs:
#   PIEZO_FUZZ_READER=model devel/lib/piezo_compensation/fuzz_readers -max_total_time=600 <scratch> fuzz/corpus/model
if(PIEZO_CLANGXX)
  set(PIEZO_FUZZ_READERS ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/fuzz_readers)
  set(fuzz_flags -std=c++17 -O1 -g -fsanitize=fuzzer-no-link,address,undefined -fno-sanitize-recover=undefined
      -Wno-unknown-pragmas -I${CMAKE_CURRENT_SOURCE_DIR}/include -I${EIGEN3_INCLUDE_DIR})
  # Only the parts the readers and the bag reader link (io, features, models, protocols and the CAN protocol
  # config, util's FlushSubnormals, format and fingerprint); the others, compiled again with clang and the sanitizers on every fresh
  # build, were linked by neither.
  file(GLOB_RECURSE fuzz_core_sources CONFIGURE_DEPENDS ${CMAKE_CURRENT_SOURCE_DIR}/src/core/io/*.cpp
       ${CMAKE_CURRENT_SOURCE_DIR}/src/core/features/*.cpp ${CMAKE_CURRENT_SOURCE_DIR}/src/core/models/*.cpp
       ${CMAKE_CURRENT_SOURCE_DIR}/src/core/protocols/*.cpp)
  list(APPEND fuzz_core_sources ${CMAKE_CURRENT_SOURCE_DIR}/src/core/can/protocol.cpp
       ${CMAKE_CURRENT_SOURCE_DIR}/src/core/util/flush_subnormals.cpp ${CMAKE_CURRENT_SOURCE_DIR}/src/core/util/format.cpp
       ${CMAKE_CURRENT_SOURCE_DIR}/src/core/util/fingerprint.cpp)
  set(fuzz_objects)
  foreach(src ${fuzz_core_sources} ${CMAKE_CURRENT_SOURCE_DIR}/fuzz/fuzz_readers.cpp)
    file(RELATIVE_PATH rel ${CMAKE_CURRENT_SOURCE_DIR} ${src})
    string(REPLACE "/" "_" obj_name ${rel})
    set(obj ${CMAKE_BINARY_DIR}/fuzz_objects/${obj_name}.o)
    add_custom_command(OUTPUT ${obj}
      COMMAND ${CMAKE_COMMAND} -E make_directory ${CMAKE_BINARY_DIR}/fuzz_objects
      COMMAND ${PIEZO_CLANGXX} ${fuzz_flags} -c ${src} -o ${obj}
      DEPENDS ${src}
      IMPLICIT_DEPENDS CXX ${src}
      COMMENT "fuzz (clang, ASan+UBSan): ${rel}")
    list(APPEND fuzz_objects ${obj})
  endforeach()
  add_custom_command(OUTPUT ${PIEZO_FUZZ_READERS}
    COMMAND ${PIEZO_CLANGXX} -fsanitize=fuzzer,address,undefined ${fuzz_objects} -lyaml-cpp -lpthread
            -o ${PIEZO_FUZZ_READERS}
    DEPENDS ${fuzz_objects}
    COMMENT "Linking libFuzzer target fuzz_readers")
  add_custom_target(fuzz_readers DEPENDS ${PIEZO_FUZZ_READERS})
  if(TARGET tests)
    add_dependencies(tests fuzz_readers)
  endif()
  # The bag reader: src/ros/bag_io.cpp instrumented, rosbag itself as installed (crashes in it still count).
  # CTest runs the seed corpus only (-runs=0): it holds four inputs that crash rosbag when read unchecked
  # (connection headers, index entries; fuzz/findings/README.md), which bag_io's record check must refuse.
  # Mutation runs take longer: run them by hand.
  set(PIEZO_FUZZ_BAG ${CATKIN_DEVEL_PREFIX}/lib/${PROJECT_NAME}/fuzz_bag)
  set(fuzz_ros_includes)
  foreach(dir ${catkin_INCLUDE_DIRS} ${CATKIN_DEVEL_PREFIX}/include)
    list(APPEND fuzz_ros_includes -I${dir})
  endforeach()
  set(fuzz_ros_objects)
  foreach(src fuzz/fuzz_bag.cpp src/ros/bag_io.cpp)
    string(REPLACE "/" "_" obj_name ${src})
    set(obj ${CMAKE_BINARY_DIR}/fuzz_objects/${obj_name}.o)
    add_custom_command(OUTPUT ${obj}
      COMMAND ${CMAKE_COMMAND} -E make_directory ${CMAKE_BINARY_DIR}/fuzz_objects
      COMMAND ${PIEZO_CLANGXX} ${fuzz_flags} ${fuzz_ros_includes} -c ${CMAKE_CURRENT_SOURCE_DIR}/${src} -o ${obj}
      DEPENDS ${CMAKE_CURRENT_SOURCE_DIR}/${src} ${PROJECT_NAME}_generate_messages_cpp
      IMPLICIT_DEPENDS CXX ${CMAKE_CURRENT_SOURCE_DIR}/${src}
      COMMENT "fuzz (clang, ASan+UBSan): ${src}")
    list(APPEND fuzz_ros_objects ${obj})
  endforeach()
  set(fuzz_core_objects ${fuzz_objects})
  list(FILTER fuzz_core_objects EXCLUDE REGEX "fuzz_fuzz_readers")
  add_custom_command(OUTPUT ${PIEZO_FUZZ_BAG}
    COMMAND ${PIEZO_CLANGXX} -fsanitize=fuzzer,address,undefined ${fuzz_ros_objects} ${fuzz_core_objects}
            ${catkin_LIBRARIES} -lbz2 -lyaml-cpp -lpthread -o ${PIEZO_FUZZ_BAG}
    DEPENDS ${fuzz_ros_objects} ${fuzz_core_objects}
    COMMENT "Linking libFuzzer target fuzz_bag")
  add_custom_target(fuzz_bag DEPENDS ${PIEZO_FUZZ_BAG})
  if(TARGET tests)
    add_dependencies(tests fuzz_bag)
  endif()
  if(CATKIN_ENABLE_TESTING)
    add_test(NAME fuzz_bag_corpus
      COMMAND sh -c "rm -rf fuzz_bag_scratch && mkdir -p fuzz_bag_scratch && exec '${PIEZO_FUZZ_BAG}' -seed=1 -runs=0 -max_len=65536 -malloc_limit_mb=1024 -rss_limit_mb=2048 -timeout=20 fuzz_bag_scratch '${CMAKE_CURRENT_SOURCE_DIR}/fuzz/corpus/bag'"
      WORKING_DIRECTORY ${CMAKE_BINARY_DIR})
    piezo_test_budget(fuzz_bag_corpus)
  endif()
  if(CATKIN_ENABLE_TESTING)
    foreach(reader csv model protocol controller_log)
      add_test(NAME fuzz_${reader}_corpus
        COMMAND sh -c "rm -rf fuzz_${reader}_scratch && mkdir -p fuzz_${reader}_scratch && PIEZO_FUZZ_READER=${reader} exec '${PIEZO_FUZZ_READERS}' -seed=1 -runs=20000 -max_len=4096 -malloc_limit_mb=1024 -rss_limit_mb=2048 -timeout=20 fuzz_${reader}_scratch '${CMAKE_CURRENT_SOURCE_DIR}/fuzz/corpus/${reader}'"
        WORKING_DIRECTORY ${CMAKE_BINARY_DIR})
      piezo_test_budget(fuzz_${reader}_corpus)
    endforeach()
  endif()
elseif(CATKIN_ENABLE_TESTING)
  foreach(reader csv model protocol controller_log bag)
    add_test(NAME fuzz_${reader}_corpus COMMAND sh -c "echo 'SKIPPED: no clang++-14 (apt-get install clang-14 libclang-rt-14-dev)'; exit 77")
    set_tests_properties(fuzz_${reader}_corpus PROPERTIES SKIP_RETURN_CODE 77)
    piezo_test_budget(fuzz_${reader}_corpus)
  endforeach()
endif()
