# Warnings, sanitizers and the helpers every module uses to add libraries,
# programs, tests and benchmarks, so that module CMakeLists stay a few lines.

set(VLFF_WARNINGS -Wall -Wextra -Werror -Wshadow -Wno-unused-parameter)
if(VLFF_SANITIZE)
  add_compile_options(-fsanitize=${VLFF_SANITIZE} -fno-omit-frame-pointer -fno-sanitize-recover=all)
  add_link_options(-fsanitize=${VLFF_SANITIZE})
endif()
if(VLFF_FUZZ)
  # Coverage instrumentation for the code under test; the fuzzer main is
  # linked only into the fuzz_* executables.
  add_compile_options(-fsanitize=fuzzer-no-link,address,undefined)
  add_link_options(-fsanitize=address,undefined)
endif()

# Our own code gets the strict warnings; third-party headers are SYSTEM.
function(vlff_strict target)
  target_compile_options(${target} PRIVATE ${VLFF_WARNINGS})
  target_compile_definitions(${target} PRIVATE _GNU_SOURCE)
endfunction()

# vlff_test(NAME SOURCES a.c b.c LIBS x y [LABELS tsan ...] [TIMEOUT s] [ARGS ...])
# Every unit test is a cmocka executable run by ctest. Label "tsan" marks the
# threaded/shm tests that the ThreadSanitizer build runs; "nosan" the ones the
# sanitizer builds leave out; "spawns" the ones whose child processes cannot
# run under a user-mode emulator (the host's python loading the build's
# library, the node end to end on a wall-clock budget): the cross-built
# aarch64 tree leaves them out. Tests that start programs of the build put
# VLFF_EMULATOR (qemu-user there, empty otherwise) before the program.
string(REPLACE ";" " " VLFF_EMULATOR "${CMAKE_CROSSCOMPILING_EMULATOR}")
set(VLFF_TEST_ENV "VLFF_SOURCE_DIR=${PROJECT_SOURCE_DIR}" "VLFF_BINARY_DIR=${PROJECT_BINARY_DIR}"
    "VLFF_DATA_DIR=${PROJECT_SOURCE_DIR}/node/vlm/data" "VLFF_EMULATOR=${VLFF_EMULATOR}")
function(vlff_test name)
  cmake_parse_arguments(T "" "TIMEOUT" "SOURCES;LIBS;LABELS;ARGS" ${ARGN})
  add_executable(${name} ${T_SOURCES})
  vlff_strict(${name})
  target_include_directories(${name} PRIVATE ${PROJECT_SOURCE_DIR}/tests/common)
  target_link_libraries(${name} PRIVATE PkgConfig::CMOCKA ${T_LIBS})
  add_test(NAME ${name} COMMAND ${name} ${T_ARGS})
  if(NOT T_TIMEOUT)
    set(T_TIMEOUT 300)
  endif()
  if(CMAKE_CROSSCOMPILING_EMULATOR)
    # qemu-user translates every instruction: the learner's tests run ~15x slower
    math(EXPR T_TIMEOUT "${T_TIMEOUT} * 4")
  endif()
  set_tests_properties(${name} PROPERTIES LABELS "unit;${T_LABELS}" TIMEOUT ${T_TIMEOUT}
    ENVIRONMENT "${VLFF_TEST_ENV}")
endfunction()

# vlff_bench(NAME SOURCES ... LIBS ...): a program under tests/bench whose last
# line is "RESULT k=v ...". scripts/bench runs bench_<NAME>.
function(vlff_bench name)
  cmake_parse_arguments(B "" "" "SOURCES;LIBS" ${ARGN})
  add_executable(bench_${name} ${B_SOURCES})
  vlff_strict(bench_${name})
  target_include_directories(bench_${name} PRIVATE ${PROJECT_SOURCE_DIR}/tests/bench)
  target_link_libraries(bench_${name} PRIVATE ${B_LIBS})
  set_target_properties(bench_${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/bench)
endfunction()

# vlff_fuzz(NAME SOURCES ... LIBS ...): a libFuzzer target, only in VLFF_FUZZ builds.
function(vlff_fuzz name)
  cmake_parse_arguments(F "" "" "SOURCES;LIBS" ${ARGN})
  if(NOT VLFF_FUZZ)
    return()
  endif()
  add_executable(fuzz_${name} ${F_SOURCES})
  vlff_strict(fuzz_${name})
  target_compile_options(fuzz_${name} PRIVATE -fsanitize=fuzzer,address,undefined)
  target_link_options(fuzz_${name} PRIVATE -fsanitize=fuzzer,address,undefined)
  target_link_libraries(fuzz_${name} PRIVATE ${F_LIBS})
  set_target_properties(fuzz_${name} PROPERTIES RUNTIME_OUTPUT_DIRECTORY ${PROJECT_BINARY_DIR}/fuzz)
  set_property(GLOBAL APPEND PROPERTY VLFF_FUZZERS fuzz_${name})
endfunction()

# Subdirectories are added only when present, so each module lands on its own.
function(vlff_add_subdirs)
  foreach(d ${ARGN})
    if(EXISTS ${CMAKE_CURRENT_SOURCE_DIR}/${d}/CMakeLists.txt)
      add_subdirectory(${d})
    endif()
  endforeach()
endfunction()
