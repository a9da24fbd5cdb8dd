/*
 * The one MPU-9150 (0x68/0x69) + AK8975 (0x0C) I2C register model.
 *
 * Plain C, no simavr dependency. Used by:
 *   - the simavr harness (emulator/harness.c), which answers the AVR's TWI bus with it;
 *   - the host's fake I2C bus (magcal/devices/fakebus.py), through ctypes on a shared build
 *     of this file, standing in for smbus2.SMBus in tests.
 * The field it serves comes from a provider callback; on both routes the provider is the
 * host's physics simulator (magcal/physics.py), so there is one physics and one register
 * model.
 *
 * Time is passed in by the caller (microseconds on any monotonic clock) so the model is
 * deterministic and needs no clock of its own.
 */
#ifndef MPU9150_MODEL_H
#define MPU9150_MODEL_H

#include <stdint.h>
#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

/* What the provider returns for one AK8975 measurement triggered at t_us. */
typedef struct {
    int16_t hx, hy, hz;   /* data registers, already clamped to -4096..4095 */
    uint8_t hofl;         /* 1 when the magnetic sensor overflowed */
    int16_t temp_raw;     /* MPU TEMP_OUT at this time */
} mpu_measurement;

/* Called when a single measurement completes; returns 0 on success. */
typedef int (*mpu_provider_fn)(void *ctx, uint64_t t_us, mpu_measurement *out);

/* Faults a test can inject (bit flags). */
enum {
    MPU_FAULT_NONE = 0,
    MPU_FAULT_WRONG_WHOAMI = 1 << 0, /* WHO_AM_I reads 0x71 instead of 0x68 */
    MPU_FAULT_NO_AK = 1 << 1,        /* 0x0C never answers, even with bypass on */
    MPU_FAULT_STUCK_DRDY = 1 << 2,   /* measurements never complete */
    MPU_FAULT_WRONG_WIA = 1 << 3,    /* WIA reads 0x00 */
};

typedef struct mpu_model mpu_model;

size_t mpu_model_size(void);
/* mpu_addr is 0x68 (AD0 low) or 0x69 (AD0 high); asa the three fuse-ROM bytes. */
void mpu_model_init(mpu_model *m, uint8_t mpu_addr, const uint8_t asa[3],
                    mpu_provider_fn provider, void *ctx);
void mpu_model_set_faults(mpu_model *m, unsigned faults);
void mpu_model_set_measure_us(mpu_model *m, uint32_t us); /* default 7300 */
/* The data registers a self-test measurement returns (raw counts; the host's physics decides
 * them: Physics.self_test_raw). Zero until set. */
void mpu_model_set_self_test(mpu_model *m, const int16_t raw[3]);

/* One I2C transaction, byte by byte. Each returns 0 for ACK, -1 for NACK. */
int mpu_model_start(mpu_model *m, uint8_t addr7, int is_read, uint64_t t_us);
int mpu_model_write(mpu_model *m, uint8_t byte, uint64_t t_us);
int mpu_model_read(mpu_model *m, uint8_t *byte, uint64_t t_us);
void mpu_model_stop(mpu_model *m, uint64_t t_us);

/* Direct register peek for tests (no side effects). */
uint8_t mpu_model_peek(const mpu_model *m, uint8_t addr7, uint8_t reg);

#ifdef __cplusplus
}
#endif
#endif
