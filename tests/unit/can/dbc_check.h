/* Checks shared by the host and VM tests: a status frame, decoded with the
 * DBC file alone, carries the values the node handed to vlff_can. */
#ifndef VLFF_TEST_DBC_CHECK_H
#define VLFF_TEST_DBC_CHECK_H

#include <stddef.h>
#include <stdint.h>

#include "dbc.h"
#include "vlff_can.h"

/* m: VLFF_TRAIN/LOSS/MAP/HEALTH/INGEST/MEMORY/PAGING (or VLFF_STATUS_FD
 * with part 0..6 naming the 8-byte part). Node-provided fields must match exactly (scaled values within
 * half a step, saturation as documented). Returns 0, or -1 with why. */
int dbc_check_status(const struct dbc_message *m, int part, const uint8_t *data, int len,
                     const struct vlff_can_status *st, int nmt_state, char *why, size_t n);

/* Load configs/vlff.dbc from $VLFF_SOURCE_DIR (or $VLFF_SRC in the VM);
 * a failure says why on stderr (every caller is a test's setup). Returns
 * 0 or -1. */
int dbc_load_vlff(struct dbc *db);

#endif
