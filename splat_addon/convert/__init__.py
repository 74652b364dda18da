"""Meshes to splats: conversion, appearance baking by Cycles, and the demo rig."""
