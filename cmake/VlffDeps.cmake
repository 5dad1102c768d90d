# Optional parts: each VLFF_WITH_<X> defaults to ON when its dependency is
# found; forcing one ON without the dependency is a configure error, so a
# packager never ships a node silently missing a driver.
find_package(PkgConfig REQUIRED)
include(CheckIncludeFile)
include(CheckLanguage)

set(VLFF_SANITIZE "" CACHE STRING "Sanitizers for every target: address,undefined | thread | empty")
option(VLFF_FUZZ "Build libFuzzer targets (needs clang)" OFF)

# Required: the config parser is libyaml; the unit tests are cmocka.
pkg_check_modules(YAML REQUIRED IMPORTED_TARGET yaml-0.1)
if(BUILD_TESTING)
  pkg_check_modules(CMOCKA REQUIRED IMPORTED_TARGET cmocka)
endif()
find_package(Threads REQUIRED)
find_library(MATH_LIB m REQUIRED)

set(_vlff_on "")
set(_vlff_off "")

# vlff_optional(NAME FOUND_VAR REASON_IF_MISSING)
macro(vlff_optional name found why)
  if(DEFINED VLFF_WITH_${name})
    if(VLFF_WITH_${name} AND NOT ${found})
      message(FATAL_ERROR "VLFF_WITH_${name}=ON but ${why}")
    endif()
  else()
    set(VLFF_WITH_${name} ${${found}})
  endif()
  set(VLFF_WITH_${name} ${VLFF_WITH_${name}} CACHE BOOL "Build the ${name} part" FORCE)
  string(TOLOWER ${name} _lname)
  if(VLFF_WITH_${name})
    list(APPEND _vlff_on ${_lname})
  elseif(${found})
    list(APPEND _vlff_off "${_lname} (disabled by option)")
  else()
    list(APPEND _vlff_off "${_lname} (${why})")
  endif()
endmacro()

pkg_check_modules(ARAVIS QUIET IMPORTED_TARGET aravis-0.8)
vlff_optional(ARAVIS ARAVIS_FOUND "pkg-config aravis-0.8 not found: apt install libaravis-dev libusb-1.0-0-dev")

pkg_check_modules(LIBCAMERA QUIET IMPORTED_TARGET libcamera)
vlff_optional(LIBCAMERA LIBCAMERA_FOUND "pkg-config libcamera not found: apt install libcamera-dev")

pkg_check_modules(GPIOD QUIET IMPORTED_TARGET libgpiod<2)
vlff_optional(GPIOD GPIOD_FOUND "pkg-config libgpiod (v1) not found: apt install libgpiod-dev")

check_include_file(linux/can/raw.h HAVE_LINUX_CAN_RAW_H)
vlff_optional(CAN HAVE_LINUX_CAN_RAW_H "linux/can/raw.h missing: apt install linux-libc-dev")

find_package(OpenCV QUIET COMPONENTS core imgproc calib3d imgcodecs dnn)
vlff_optional(OPENCV OpenCV_FOUND "OpenCV core/imgproc/calib3d/imgcodecs/dnn not found: apt install libopencv-dnn-dev libopencv-calib3d-dev libopencv-imgcodecs-dev")

pkg_check_modules(SYSTEMD QUIET IMPORTED_TARGET libsystemd)
vlff_optional(SYSTEMD SYSTEMD_FOUND "pkg-config libsystemd not found: apt install libsystemd-dev")

# vlff-eval's JSON report (strings escaped by the library, not by hand).
pkg_check_modules(JSONC REQUIRED IMPORTED_TARGET json-c)

find_package(HDF5 QUIET COMPONENTS C)
vlff_optional(HDF5 HDF5_FOUND "HDF5 C library not found: apt install libhdf5-dev")

# vlff-dds: Eclipse Cyclone DDS (ROS 2's rmw_cyclonedds DDS) and its IDL
# compiler, which generates the C of node/dds/idl at build time.
find_package(CycloneDDS CONFIG QUIET)
find_program(VLFF_IDLC idlc)
if(CycloneDDS_FOUND AND VLFF_IDLC)
  set(_vlff_dds_found TRUE)
else()
  set(_vlff_dds_found FALSE)
endif()
vlff_optional(DDS _vlff_dds_found "Cyclone DDS or its idlc not found: apt install cyclonedds-dev cyclonedds-tools")

if(VLFF_FUZZ AND NOT CMAKE_C_COMPILER_ID STREQUAL "Clang")
  message(FATAL_ERROR "VLFF_FUZZ=ON needs clang (configure with CC=clang)")
endif()

string(REPLACE ";" " " _on "${_vlff_on}")
string(REPLACE ";" ", " _off "${_vlff_off}")
if(NOT _off)
  set(_off "none")
endif()
message(STATUS "vlff parts on: ${_on}; off: ${_off}")
