/* firmware.h: the sensor's command and frame state machine, the C form of onboard.firmware.Firmware: the single
 * authority for what the sensor accepts, on every link. A command comes in as the bytes of one decoded protocol
 * message (the transport removed its framing) and its reply goes out as the bytes of one message, encoded by the
 * generated wire codec (st_messages.h). Commands, what they require and the NAK code when refused:
 *
 *   GET_STATUS      always accepted
 *   STREAM_CONTROL  always accepted; Ack value of a start = the frame counter of the stream's first exposure
 *                   (next_frame when it started; a start while streaming carries the same value), of a stop 0
 *   STAGE_BEGIN     length == 92 (BAD_LENGTH); session record persisted (BANK_WRITE_FAILED); Ack value = nonce
 *   STAGE_CHUNK     an upload in progress (NOT_STAGED); chunk inside the table (BAD_LENGTH); un-verifies
 *   STAGE_VERIFY    staged set complete (NOT_STAGED), CRC (BAD_CRC), plausibility and sigma (INVALID_PARAMS)
 *   READ_STAGED     staged set complete (NOT_STAGED)
 *   COMMIT          the session's nonce and the active generation (STALE_SESSION); verified, same CRC
 *                   (NOT_VERIFIED); sector read-back (BANK_WRITE_FAILED)
 *   READ_ACTIVE     a committed set exists (NOT_STAGED)
 *   READ_ESTIMATE   an estimator with at least one update (NO_ESTIMATE; a build without an estimator,
 *                   estimator_none.c, always answers NO_ESTIMATE "this sensor has no onboard estimator")
 *   any other message type: UNKNOWN_COMMAND "<Name> is not a command"
 *
 * Frames: firmware_process_frame counts an exposure and gives it to the estimator when the modelled budget leaves
 * the processor idle at the exposure's time (onboard.firmware.EstimatorBudget), as Firmware.process_frame does.
 * No I/O, no clock (time comes with each frame), no dynamic memory; the estimator's state is the caller's. */
#ifndef FIRMWARE_H
#define FIRMWARE_H

#include <stddef.h>
#include <stdint.h>

#include "banks.h"
#include "estimator_seam.h"
#include "st_messages.h"

#ifdef __cplusplus
extern "C" {
#endif

enum firmware_result {
    FIRMWARE_REPLY = 0,       /* reply[0..*reply_len) holds the reply */
    FIRMWARE_UNDECODABLE = 1, /* the bytes are not a message (st_decode refused them): no reply, as on every link */
    FIRMWARE_POWER_CUT = 2,   /* the flash HAL reported a power cut: the device stopped */
    FIRMWARE_NO_SPACE = 3     /* the reply buffer is smaller than FIRMWARE_REPLY_MAX_BYTES */
};

/* the longest reply (a ParamTable, 104 bytes; an Estimate, 98; a Nak, 126) */
#define FIRMWARE_REPLY_MAX_BYTES ST_NAK_MAX_BYTES

/* onboard.firmware.EstimatorBudget */
typedef struct {
    double flops_per_s;
    double min_frame_period_s;
} firmware_budget_t;

/* onboard.firmware.Counters */
typedef struct {
    uint32_t frames_processed;
    uint32_t last_frame;
    uint32_t estimator_faults;
    uint32_t estimator_runs;
    uint32_t estimator_skipped;
} firmware_counters_t;

typedef struct {
    banks_store_t store;
    uint8_t streaming;
    firmware_counters_t counters;
    uint32_t next_frame;         /* the camera's next exposure's counter: the last + 1, or firmware_set_next_frame */
    uint32_t stream_first_frame; /* the counter the current stream's start was acknowledged with */
    firmware_budget_t budget;
    uint32_t has_sensor_time;
    int64_t sensor_time_us;
    uint32_t has_busy_until;
    int64_t busy_until_us;
    estimator_seam_state_t *est; /* NULL: a sensor without an onboard estimator */
    estimator_seam_config_t est_config;
    uint32_t est_running; /* a state started from the active set (Python: _est_state is not None) */
    uint32_t est_generation;
    uint32_t est_last_frame;
    st_message_t command;                                /* the decoded command (3.6 kB: a CentroidFrame fits) */
    double frame_r_ref[3u * ESTIMATOR_SEAM_MAX_STARS];   /* a frame's reference vectors, 0 where unidentified */
    uint8_t frame_identified[ESTIMATOR_SEAM_MAX_STARS];  /* and which stars are identified */
} firmware_t;

/* EstimatorBudget() defaults: 50 Mflop/s, 0.1 s */
firmware_budget_t firmware_default_budget(void);
/* A firmware over a booted store (banks_boot / banks_factory). `est`: caller-owned state of
 * estimator_seam_state_bytes() bytes, or NULL (also when estimator_seam_available() is 0). 0, or nonzero for a
 * budget that is not finite and > 0. */
int firmware_init(firmware_t *fw, const banks_store_t *store, estimator_seam_state_t *est,
                  const estimator_seam_config_t *config, const firmware_budget_t *budget);
/* One command message -> its reply (enum firmware_result). */
int firmware_handle(firmware_t *fw, const uint8_t *command, size_t n, uint8_t *reply, size_t cap,
                    size_t *reply_len);
/* The camera's driver announces the frame counter of its next exposure (Firmware.set_next_frame): for a camera
 * whose counter does not simply follow the last exposure processed. */
void firmware_set_next_frame(firmware_t *fw, uint32_t frame);
/* One exposure (Firmware.process_frame): n stars, their ids (0 = not identified), centroids [px] and reference unit
 * vectors (row-major n x 3, NaN rows where the catalogue has none; r_ref NULL = no catalogue for this frame).
 * Returns 1 when the estimator ran on it. */
int firmware_process_frame(firmware_t *fw, uint32_t frame, int64_t t_us, uint32_t n, const uint32_t *star_id,
                           const double *x_px, const double *y_px, const double *r_ref);

#ifdef __cplusplus
}
#endif
#endif /* FIRMWARE_H */
