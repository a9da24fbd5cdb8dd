/*
 * The one IMU + magnetometer I2C register model: an MPU-9150 (AK8975), an MPU-9250/9255
 * (AK8963, 14- or 16-bit output as CNTL1 selects) or an ICM-20948 (AK09916), the IMU at
 * 0x68/0x69 and the magnetometer at 0x0C behind the IMU's I2C bypass.
 *
 * Plain C, no simavr dependency. Used by:
 *   - the simavr harness (emulator/harness.c), which answers the AVR's TWI bus with it;
 *   - the host's fake I2C bus (magcal/devices/fakebus.py), through ctypes on a shared build
 *     of this file, standing in for smbus2.SMBus in tests.
 * The field it serves comes from a provider callback; on both routes the provider is the
 * host's physics simulator (magcal/sim/physics.py), so there is one physics and one register
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

/* What the provider returns for one magnetometer measurement triggered at t_us, in the
 * chip's own counts at the resolution the measurement was taken with (mpu_model_mag_bits):
 * the model clamps them to that range (AK8975 -4096..4095, AK8963 +-8190 (14-bit) or
 * +-32760 (16-bit), AK09916 +-32752). */
typedef struct {
    int16_t hx, hy, hz;
    uint8_t hofl;         /* 1 when the magnetic sensor overflowed */
    int16_t temp_raw;     /* the IMU's TEMP_OUT at this time */
    int16_t ax, ay, az;   /* the IMU's ACCEL_*OUT at this time: counts at +-2 g (16384 per g) */
} mpu_measurement;

/* Called when a single measurement completes; returns 0 on success. */
typedef int (*mpu_provider_fn)(void *ctx, uint64_t t_us, mpu_measurement *out);

/* The chips (mpu_model_set_chip). */
enum {
    MPU_CHIP_MPU9150 = 0,  /* WHO_AM_I 0x68, AK8975 */
    MPU_CHIP_MPU9250 = 1,  /* WHO_AM_I 0x71, AK8963 */
    MPU_CHIP_MPU9255 = 2,  /* WHO_AM_I 0x73, AK8963 */
    MPU_CHIP_ICM20948 = 3, /* WHO_AM_I 0xEA (bank 0, register 0x00), AK09916 */
    MPU_CHIP_COUNT
};

/* Faults a test can inject (bit flags). */
enum {
    MPU_FAULT_NONE = 0,
    MPU_FAULT_WRONG_WHOAMI = 1 << 0, /* WHO_AM_I reads an id no supported chip has (see .c) */
    MPU_FAULT_NO_AK = 1 << 1,        /* 0x0C never answers, even with bypass on */
    MPU_FAULT_STUCK_DRDY = 1 << 2,   /* measurements never complete */
    MPU_FAULT_WRONG_WIA = 1 << 3,    /* WIA (and the AK09916's WIA2) read 0x00 */
};

typedef struct mpu_model mpu_model;

size_t mpu_model_size(void);
/* An MPU-9150. mpu_addr is 0x68 (AD0 low) or 0x69 (AD0 high); asa the three fuse-ROM bytes
 * (the AK8975's or AK8963's; the AK09916 has none). */
void mpu_model_init(mpu_model *m, uint8_t mpu_addr, const uint8_t asa[3],
                    mpu_provider_fn provider, void *ctx);
/* Make it another chip (MPU_CHIP_*), as if powered up as that chip; -1 for an unknown one. */
int mpu_model_set_chip(mpu_model *m, int chip);
void mpu_model_set_faults(mpu_model *m, unsigned faults);
void mpu_model_set_measure_us(mpu_model *m, uint32_t us); /* default 7300 */
/* The data registers a self-test measurement returns (raw counts in the chip's quantum; the
 * host's physics decides them: Physics.self_test_raw). Zero until set. */
void mpu_model_set_self_test(mpu_model *m, const int16_t raw[3]);
/* The output resolution of the measurement last triggered: 13 (AK8975), 14 or 16 (AK8963,
 * CNTL1 BIT), 16 (AK09916). What the provider's counts must be in. */
int mpu_model_mag_bits(const mpu_model *m);

/* One I2C transaction, byte by byte. Each returns 0 for ACK, -1 for NACK. */
int mpu_model_start(mpu_model *m, uint8_t addr7, int is_read, uint64_t t_us);
int mpu_model_write(mpu_model *m, uint8_t byte, uint64_t t_us);
int mpu_model_read(mpu_model *m, uint8_t *byte, uint64_t t_us);
void mpu_model_stop(mpu_model *m, uint64_t t_us);

/* Direct register peek for tests (no side effects; the IMU's register in its current bank). */
uint8_t mpu_model_peek(const mpu_model *m, uint8_t addr7, uint8_t reg);

#ifdef __cplusplus
}
#endif
#endif
