"""OpenCL C sources (package data: the .cl and .h files beside this file)."""
