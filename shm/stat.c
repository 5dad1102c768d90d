/*
 * vlff_shm_stat: any segment, whatever its kind. The one place that knows
 * every kind: it reads the header's kind, attaches with that kind's spec
 * (ring.c, map.c, prompts.c) and lets the kind's stat fill its part, so
 * seg.c, which they all build on, needs to know none of them.
 */
#include <errno.h>
#include <string.h>

#include "shm_internal.h"

API int vlff_shm_stat(const char *name, struct vlff_shm_info *info) {
  if (!info) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_shm_stat: info is NULL");
    return -1;
  }
  struct seg_hdr h;
  if (shm_seg_peek(name, &h) < 0)
    return -1;
  struct seg_spec spec;
  switch (h.kind) {
  case VLFF_SHM_KIND_RING: spec = shm_ring_spec(0); break;
  case VLFF_SHM_KIND_MAP: spec = shm_map_spec; break;
  case VLFF_SHM_KIND_PROMPTS: spec = shm_prompts_spec; break;
  default: shm_err(VLFF_SHM_ERR_KIND, EPROTO, "%s: unknown segment kind %u", VLFF_Q(name), h.kind); return -1;
  }
  struct seg s;
  if (shm_seg_attach(&s, name, &spec, false, NULL) < 0)
    return -1;
  memset(info, 0, sizeof *info);
  info->kind = s.h->kind;
  info->abi_version = s.h->abi_version;
  info->record_kind = s.h->record_kind;
  info->generation = atomic_load(&s.h->generation);
  info->creator_pid = atomic_load(&s.h->creator_pid);
  info->creator_alive = shm_creator_alive(info->creator_pid, atomic_load(&s.h->creator_start));
  info->total_size = s.h->total_size;
  info->last_ns = atomic_load(&s.h->last_ns);
  spec.stat(&s, info);
  shm_seg_close(&s);
  return 0;
}
