/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * schemas.c - the channels' topics and JSON Schemas, as advertised to clients.
 *
 * The foxglove.* schemas follow the published Foxglove message definitions
 * (field names, types and required fields; test_view_foxglove compares them with
 * the npm package @foxglove/schemas); Foxglove picks its panels by schema name and
 * decodes JSON messages with these schemas, so a field misspelt here is a blank
 * panel there.
 * Byte arrays are base64 strings, as Foxglove expects of JSON-encoded bytes; images
 * are compressed (JPEG for the camera, PNG for labels) rather than raw pixels.
 */
#include "inputs.h"
#include "view.h"

#define TIME_S "{\"type\":\"object\",\"properties\":{\"sec\":{\"type\":\"integer\",\"minimum\":0},\"nsec\":{\"type\":\"integer\",\"minimum\":0,\"maximum\":999999999}},\"required\":[\"sec\",\"nsec\"]}"
#define VEC3_S "{\"type\":\"object\",\"properties\":{\"x\":{\"type\":\"number\"},\"y\":{\"type\":\"number\"},\"z\":{\"type\":\"number\"}},\"required\":[\"x\",\"y\",\"z\"]}"
#define QUAT_S "{\"type\":\"object\",\"properties\":{\"x\":{\"type\":\"number\"},\"y\":{\"type\":\"number\"},\"z\":{\"type\":\"number\"},\"w\":{\"type\":\"number\"}},\"required\":[\"x\",\"y\",\"z\",\"w\"]}"
#define COLOR_S "{\"type\":\"object\",\"properties\":{\"r\":{\"type\":\"number\"},\"g\":{\"type\":\"number\"},\"b\":{\"type\":\"number\"},\"a\":{\"type\":\"number\"}},\"required\":[\"r\",\"g\",\"b\",\"a\"]}"
#define POSE_S "{\"type\":\"object\",\"properties\":{\"position\":" VEC3_S ",\"orientation\":" QUAT_S "},\"required\":[\"position\",\"orientation\"]}"
#define ARR_S "{\"type\":\"array\"}"

static const char scene_schema[] =
    "{\"title\":\"foxglove.SceneUpdate\",\"type\":\"object\",\"properties\":{"
    "\"deletions\":{\"type\":\"array\",\"items\":{\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"type\":{\"type\":\"integer\",\"enum\":[0,1]},\"id\":{\"type\":\"string\"}},"
    "\"required\":[\"timestamp\",\"type\",\"id\"]}},"
    "\"entities\":{\"type\":\"array\",\"items\":{\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"frame_id\":{\"type\":\"string\"},\"id\":{\"type\":\"string\"},"
    "\"lifetime\":" TIME_S ",\"frame_locked\":{\"type\":\"boolean\"},\"metadata\":" ARR_S ","
    "\"arrows\":" ARR_S ",\"cubes\":{\"type\":\"array\",\"items\":{\"type\":\"object\",\"properties\":{"
    "\"pose\":" POSE_S ",\"size\":" VEC3_S ",\"color\":" COLOR_S "},\"required\":[\"pose\",\"size\",\"color\"]}},"
    "\"spheres\":" ARR_S ",\"cylinders\":" ARR_S ",\"lines\":" ARR_S ",\"triangles\":" ARR_S ","
    "\"texts\":" ARR_S ",\"models\":" ARR_S "},"
    "\"required\":[\"timestamp\",\"frame_id\",\"id\",\"lifetime\",\"frame_locked\",\"metadata\",\"arrows\",\"cubes\","
    "\"spheres\",\"cylinders\",\"lines\",\"triangles\",\"texts\",\"models\"]}}},"
    "\"required\":[\"deletions\",\"entities\"]}";

static const char voxels_schema[] =
    "{\"title\":\"vlff.VoxelDelta\",\"description\":\"Voxels of the labelled map that changed since the "
    "previous message (all occupied voxels when full is true). voxels holds triples (index, label, "
    "confidence); index = i + dims[0]*(j + dims[1]*k); label 65534 = free, 65535 = unknown. A version "
    "goes out in pieces, piece 0..pieces-1 in a row: full is true on the first piece of a whole map "
    "(forget every voxel it does not list), and later pieces add their voxels as a change does.\","
    "\"type\":\"object\",\"properties\":{"
    "\"version\":{\"type\":\"integer\"},\"full\":{\"type\":\"boolean\"},"
    "\"piece\":{\"type\":\"integer\",\"minimum\":0},\"pieces\":{\"type\":\"integer\",\"minimum\":1},"
    "\"publish_mono_ns\":{\"type\":\"integer\"},"
    "\"origin\":{\"type\":\"array\",\"items\":{\"type\":\"number\"},\"minItems\":3,\"maxItems\":3},"
    "\"voxel_size\":{\"type\":\"number\"},"
    "\"dims\":{\"type\":\"array\",\"items\":{\"type\":\"integer\"},\"minItems\":3,\"maxItems\":3},"
    "\"prompts\":{\"type\":\"array\",\"items\":{\"type\":\"string\"}},"
    "\"colors\":{\"type\":\"array\",\"items\":{\"type\":\"string\"}},"
    "\"occupied\":{\"type\":\"integer\"},"
    "\"voxels\":{\"type\":\"array\",\"items\":{\"type\":\"integer\"}}},"
    "\"required\":[\"version\",\"full\",\"origin\",\"voxel_size\",\"dims\",\"prompts\",\"colors\",\"occupied\",\"voxels\"]}";

static const char compressed_schema[] =
    "{\"title\":\"foxglove.CompressedImage\",\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"frame_id\":{\"type\":\"string\"},"
    "\"data\":{\"type\":\"string\",\"contentEncoding\":\"base64\"},\"format\":{\"type\":\"string\"}},"
    "\"required\":[\"timestamp\",\"frame_id\",\"data\",\"format\"]}";

static const char status_schema[] =
    "{\"title\":\"vlff.Status\",\"description\":\"What the map segment, its writer, the frame ring and the "
    "viewer report.\",\"type\":\"object\",\"properties\":{"
    "\"map\":{\"type\":\"object\",\"properties\":{\"segment\":{\"type\":\"string\"},\"attached\":{\"type\":\"boolean\"},"
    "\"version\":{\"type\":\"integer\"},\"generation\":{\"type\":\"integer\"},\"age_s\":{\"type\":[\"number\",\"null\"]},"
    "\"writer_alive\":{\"type\":\"boolean\"},\"prompts\":{\"type\":\"array\",\"items\":{\"type\":\"string\"}},"
    "\"dims\":{\"type\":\"array\"},\"voxel_size\":{\"type\":\"number\"},\"origin\":{\"type\":\"array\"},"
    "\"occupied\":{\"type\":\"integer\"},\"free\":{\"type\":\"integer\"},\"unknown\":{\"type\":\"integer\"},"
    "\"label_counts\":{\"type\":\"array\",\"items\":{\"type\":\"integer\"}}},\"required\":[\"segment\",\"attached\",\"version\"]},"
    "\"learner\":{\"type\":[\"object\",\"null\"],\"description\":\"the map writer's own status (vlff_map_get_status), "
    "null before it set one\",\"properties\":{\"state\":{\"type\":\"string\"},\"state_code\":{\"type\":\"integer\"},"
    "\"error_flags\":{\"type\":\"integer\"},\"age_s\":{\"type\":\"number\"},\"updates\":{\"type\":\"integer\"},"
    "\"frames_in\":{\"type\":\"integer\"},\"frames_lost\":{\"type\":\"integer\"},"
    "\"frames_refused\":{\"type\":\"integer\"},\"refused\":{\"type\":\"array\",\"items\":{\"type\":\"object\","
    "\"properties\":{\"reason\":{\"type\":\"string\"},\"count\":{\"type\":\"integer\"}}}},"
    "\"keyframes\":{\"type\":\"integer\"},\"keyframes_evicted\":{\"type\":\"integer\"},"
    "\"iterations\":{\"type\":\"integer\"},\"iterations_per_s\":{\"type\":[\"number\",\"null\"]},"
    "\"fps_in\":{\"type\":[\"number\",\"null\"]},\"loss\":{\"type\":[\"number\",\"null\"]},"
    "\"loss_rgb\":{\"type\":[\"number\",\"null\"]},\"loss_depth\":{\"type\":[\"number\",\"null\"]},"
    "\"loss_feat\":{\"type\":[\"number\",\"null\"]},\"psnr\":{\"type\":[\"number\",\"null\"]},"
    "\"cpu_budget\":{\"type\":[\"number\",\"null\"]},\"cpu_used\":{\"type\":[\"number\",\"null\"]},"
    "\"frame_to_map_ms_p50\":{\"type\":[\"number\",\"null\"]},\"frame_to_map_ms_p99\":{\"type\":[\"number\",\"null\"]},"
    "\"publish_interval_s\":{\"type\":[\"number\",\"null\"]},\"label_flips\":{\"type\":\"integer\"},"
    "\"label_flips_refresh\":{\"type\":\"integer\"},\"label_flips_total\":{\"type\":\"integer\"},"
    "\"label_flip_frac\":{\"type\":[\"number\",\"null\"],\"description\":\"-1 while unknown, as the other "
    "numbers here\"},\"mem_keyframes_mb\":{\"type\":[\"number\",\"null\"]},"
    "\"mem_keyframes_limit_mb\":{\"type\":[\"number\",\"null\"]},\"mem_evidence_mb\":{\"type\":[\"number\",\"null\"]},"
    "\"mem_evidence_limit_mb\":{\"type\":[\"number\",\"null\"]},\"mem_field_mb\":{\"type\":[\"number\",\"null\"]},"
    "\"mem_rss_mb\":{\"type\":[\"number\",\"null\"],\"description\":\"MiB, the writer process's resident set\"},"
    "\"keyframes_paged\":{\"type\":\"integer\",\"description\":\"keyframes in the page file now\"},"
    "\"keyframes_paged_out\":{\"type\":\"integer\"},\"keyframes_paged_in\":{\"type\":\"integer\"},"
    "\"keyframes_dropped\":{\"type\":\"integer\"},\"keyframes_page_mb\":{\"type\":[\"number\",\"null\"]},"
    "\"keyframes_page_limit_mb\":{\"type\":[\"number\",\"null\"],\"description\":\"MiB, keyframes.page_mb; 0 = no "
    "page file\"},\"evidence_paged\":{\"type\":\"integer\",\"description\":\"voxels whose evidence is in the page "
    "file now\"},\"evidence_paged_out\":{\"type\":\"integer\"},\"evidence_paged_in\":{\"type\":\"integer\"},"
    "\"evidence_dropped\":{\"type\":\"integer\"},\"box_growths\":{\"type\":\"integer\"},"
    "\"box_refused\":{\"type\":\"integer\"},\"box_lo\":{\"type\":\"array\",\"items\":{\"type\":[\"number\",\"null\"]},"
    "\"description\":\"the map's box, least corner, x y z in metres\"},\"box_hi\":{\"type\":\"array\","
    "\"items\":{\"type\":[\"number\",\"null\"]},\"description\":\"the map's box, greatest corner\"}}},"
    "\"frames\":{\"type\":\"object\",\"properties\":{\"segment\":{\"type\":\"string\"},\"attached\":{\"type\":\"boolean\"},"
    "\"head\":{\"type\":\"integer\"},\"generation\":{\"type\":\"integer\"},\"fps\":{\"type\":\"number\"}}},"
    "\"viewer\":{\"type\":\"object\",\"properties\":{\"clients\":{\"type\":\"integer\"},\"connections\":{\"type\":\"integer\"},"
    "\"dropped_slow\":{\"type\":\"integer\"},\"refused\":{\"type\":\"integer\"},\"bad_requests\":{\"type\":\"integer\"},"
    "\"prompts_posted\":{\"type\":\"integer\"},\"messages_sent\":{\"type\":\"integer\"},\"bytes_sent\":{\"type\":\"integer\"},"
    "\"http_refused\":{\"type\":\"object\",\"description\":\"HTTP requests refused, by status: 400 malformed, 403 Host or "
    "Origin not allowed, 404 no such file, 405 not GET or HEAD, 408 no whole head in time, 414 target too long, 426 "
    "WebSocket version not 13, 431 head too large, 503 too many connections, 505 not HTTP/1.x\",\"properties\":{"
    "\"400\":{\"type\":\"integer\"},\"403\":{\"type\":\"integer\"},\"404\":{\"type\":\"integer\"},"
    "\"405\":{\"type\":\"integer\"},\"408\":{\"type\":\"integer\"},\"414\":{\"type\":\"integer\"},"
    "\"426\":{\"type\":\"integer\"},"
    "\"431\":{\"type\":\"integer\"},\"503\":{\"type\":\"integer\"},\"505\":{\"type\":\"integer\"}}}}}},"
    "\"required\":[\"map\",\"learner\",\"frames\",\"viewer\"]}";

static const char log_schema[] =
    "{\"title\":\"foxglove.Log\",\"type\":\"object\",\"properties\":{"
    "\"timestamp\":" TIME_S ",\"level\":{\"type\":\"integer\",\"enum\":[0,1,2,3,4,5],\"description\":\"0 unknown, "
    "1 debug, 2 info, 3 warning, 4 error, 5 fatal\"},\"message\":{\"type\":\"string\"},\"name\":{\"type\":\"string\"},"
    "\"file\":{\"type\":\"string\"},\"line\":{\"type\":\"integer\",\"minimum\":0}},"
    "\"required\":[\"timestamp\",\"level\",\"message\",\"name\",\"file\",\"line\"]}";

static struct vlff_view_channel_def defs[VLFF_VIEW_CH_COUNT] = {
    {"/map", "foxglove.SceneUpdate", scene_schema, "json"},
    {"/map/voxels", "vlff.VoxelDelta", voxels_schema, "json"},
    {"/camera/image", "foxglove.CompressedImage", compressed_schema, "json"},
    {"/camera/labels", "foxglove.CompressedImage", compressed_schema, "json"},
    {"/tf", "foxglove.FrameTransform", vlff_schema_frame_transform, "json"},
    {"/vlff/status", "vlff.Status", status_schema, "json"},
    {"/camera/calibration", "foxglove.CameraCalibration", vlff_schema_camera_calibration, "json"},
    {"/log", "foxglove.Log", log_schema, "json"},
    /* the protobuf channels' schemas are built at the first call */
    {"/map/points", "foxglove.PointCloud", NULL, "protobuf"},
    {"/camera/depth", "foxglove.RawImage", NULL, "protobuf"},
    {"/map/grid", "foxglove.Grid", NULL, "protobuf"},
};

const struct vlff_view_channel_def *vlff_view_channel(int ch) {
  if (ch < 1 || ch > VLFF_VIEW_CH_COUNT) return NULL;
  if (!defs[ch - 1].schema) defs[ch - 1].schema = vlff_view_descriptor_b64(ch);
  return &defs[ch - 1];
}
